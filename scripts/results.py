"""Write docs/results.md from a store: the summary node's tables (the studies on the test split
beside the paper's figures, the paper's targets), the control study's and, where they have run,
the ablation's and the learning curve's; and the README's results table (between its `results`
markers): each study's normal-force MAE per method.

    python scripts/results.py [--store artifacts] [--profile NAME] [--out docs/results.md]
                              [--curves-param KEY=VALUE ...]

The store must hold the current summary for these params (`pipeline run` first; add
`pipeline run ablation` for the ablation's table and `pipeline run curves` for the learning
curve's; --curves-param: the -p overrides the curves ran with, e.g. curves.factors=[4]).
"""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from store_lookup import REPO, artifact_path, built_path  # noqa: E402


BEGIN, END = "<!-- results: python scripts/results.py --profile seeds -->", "<!-- /results -->"


def _markdown(path: str) -> str:
    from pipeline.artifact import Artifact
    with Artifact(path) as art:
        return str(art.attrs["markdown"])


def readme_table(summary_path: str) -> str:
    """Each force study's first row (normal-force MAE, mean over its pairs) as one table."""
    from pipeline.artifact import Artifact
    with Artifact(summary_path) as art:
        tables = art.attrs["report_tables"]
    rows, header = [], []
    for t in tables:
        if t["header"][:2] == ["test split", "paper"]:
            study = t["title"].split(" ")[0]
            rows.append([f"{study}: {t['rows'][0][0]}", *t["rows"][0][1:]])
            header = ["study (test split)", *t["header"][1:]]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def control_table(control_path: str) -> str:
    """The control study (paper Fig. 7): per grasp and slip run, the steady normal-force error
    of the gripper driven by the transferred model and by the supervised one, and the count of
    runs inside the success band."""
    from pipeline.artifact import Artifact
    with Artifact(control_path) as art:
        m, attrs = art.metrics, art.attrs
    band, targets = float(attrs["tolerance_N"]), attrs["targets_N"]
    drivers = [("genforce_plus", "control")]
    if attrs.get("supervised"):
        drivers.append(("supervised", "control/supervised"))
    runs = sorted({tuple(k.split("/")[1:3]) for k in m if k.split("/")[1] in ("grasp", "slip")},
                  key=lambda r: (r[0] != "grasp", r[1]))
    head = "| run | target (N) | " + " | ".join(f"{d}: force error (N), success" for d, _ in drivers) + " |"
    lines = [head, "|" + "---|" * (2 + len(drivers))]
    for kind, name in runs:
        cells = [f"{m[f'{p}/{kind}/{name}/force_error_N']:.3g}, {'yes' if m[f'{p}/{kind}/{name}/success'] else 'no'}"
                 for _, p in drivers]
        lines.append(f"| {kind} {name} | {targets[name]:g} | " + " | ".join(cells) + " |")
    counts = [f"{sum(int(m[f'{p}/{k}/{n}/success']) for k, n in runs)}/{len(runs)}" for _, p in drivers]
    lines.append("| runs in the band | | " + " | ".join(counts) + " |")
    return (f"\n## Control (paper Fig. 7)\n\nThe gripper twin with {attrs['camera'].get('skin', 'drawn')} "
            f"fingers, driven by the first seed's models; a run succeeds when the steady normal force "
            f"is within {band:g} N of the target, uncrushed (a slip run: also detected within the "
            f"window and stopped).\n\n" + "\n".join(lines) + "\n")


def replace_block(text: str, block: str) -> str:
    """`text` with what lies between the results markers replaced by `block`."""
    if BEGIN not in text or END not in text:
        sys.exit(f"results: README.md has no {BEGIN} ... {END} block")
    head, rest = text.split(BEGIN, 1)
    return head + BEGIN + "\n" + block + "\n" + END + rest.split(END, 1)[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default="artifacts")
    ap.add_argument("--profile", default=None)
    ap.add_argument("--out", default=str(REPO / "docs" / "results.md"))
    ap.add_argument("--readme", default=str(REPO / "README.md"), help="'' leaves the README alone")
    ap.add_argument("--curves-param", action="append", default=[], metavar="KEY=VALUE",
                    help="a -p override the curves ran with (repeatable)")
    args = ap.parse_args()
    summary_path = artifact_path(args.store, "summary", "results", profile=args.profile)
    parts = [_markdown(summary_path)]
    ablation = built_path(args.store, "ablation", profile=args.profile)
    if ablation:
        parts.append(_markdown(ablation))
    curve_args = [a for kv in args.curves_param for a in ("-p", kv)]
    curve_parts = []
    for study in ("homo", "material", "hetero"):
        curve = built_path(args.store, f"curves[study={study}]", tuple(args.curves_param), args.profile)
        if curve and _markdown(curve):
            curve_parts.append(_markdown(curve))
    if curve_parts:
        rows = [line for k, part in enumerate(curve_parts) for line in part.splitlines()[(0 if k == 0 else 2):]]
        parts.append("\n## Learning curve\n\nValidation MAE (total, N) of the first seed's oracle and "
                     "genforce_comp at the profile's training length (1x) and longer, the mean over each "
                     "study's pairs (`pipeline run curves`" + (f" {' '.join(curve_args)}" if curve_args else "") +
                     "); converged: 1x within 10% of the longest.\n\n" + "\n".join(rows) + "\n")
    control = built_path(args.store, "control", profile=args.profile)
    if control:
        parts.append(control_table(control))
    profile_name = args.profile or "default"
    text = ("# Results\n\n"
            f"Generated by `python scripts/results.py` from a store built with the {profile_name} profile "
            "(`pipeline run" + ("" if profile_name == "default" else f" --profile {profile_name}") + "`" +
            (", then `pipeline run ablation`" if ablation else "") + ").  "
            "Every figure is on the test split (the authors' unseen indenters: sphere_s, triangle, pacman, "
            "cone, wave, torus), scored once; the ablation's are on the validation indenters, which made "
            "every choice.  MAE in N.\n\n" + "\n".join(parts))
    Path(args.out).write_text(text)
    print(args.out)
    if args.readme:
        readme = Path(args.readme)
        readme.write_text(replace_block(readme.read_text(), readme_table(summary_path)))
        print(readme)


if __name__ == "__main__":
    main()
