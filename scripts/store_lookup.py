"""A node instance's artifact file in a store, for the scripts: through `pipeline get`, so the
store's index and this checkout's params and code decide, as on the command line."""
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _get(store: str, instance: str, params: tuple[str, ...], profile: str | None):
    overrides = [arg for kv in params for arg in ("-p", kv)]
    overrides += ["--profile", profile] if profile else []
    return subprocess.run([sys.executable, "-m", "pipeline", "get", instance, "--store", str(store),
                           *overrides], cwd=REPO, capture_output=True, text=True)


def artifact_path(store: str, instance: str, tool: str, params: tuple[str, ...] = (),
                  profile: str | None = None) -> str:
    """The path `pipeline get` prints (with `params` as its -p KEY=VALUE overrides, under
    `profile` when given); exits with one line naming `tool` and `instance` when the store does
    not hold it up to date."""
    out = _get(store, instance, params, profile)
    if out.returncode:
        sys.exit(f"{tool}: {instance}: {out.stderr.strip() or out.stdout.strip()}")
    return out.stdout.strip()


def built_path(store: str, instance: str, params: tuple[str, ...] = (),
               profile: str | None = None) -> str | None:
    """As artifact_path, None where the store does not hold the instance up to date (a node
    run only when named)."""
    out = _get(store, instance, params, profile)
    return None if out.returncode else out.stdout.strip()
