"""The summary's tables print mean ± sd over the regressor seeds, and count a target as met,
or a method as better, only beyond that spread."""
from stages.summary import force_table, targets


def _metrics():
    m = {}
    for pair, so, gf, sd_so, sd_gf in (("a_b", 3.0, 2.0, 0.3, 0.3),    # 1.0 better, spread 0.42: counts
                                       ("b_a", 3.0, 2.8, 0.3, 0.3)):   # 0.2 better, inside it: does not
        for method, v, sd in (("source_only", so, sd_so), ("genforce", gf, sd_gf)):
            m[f"homo/{pair}/{method}/mae_total"] = v
            m[f"homo/{pair}/{method}/mae_total_sd"] = sd
    m["homo/mean/genforce/mae_fz"], m["homo/mean/genforce/mae_fz_sd"] = 1.234, 0.0567
    m["homo/mean/oracle/mae_fz"] = 0.5                                  # no spread: the value alone
    m["homo/mean/oracle/mae_fz_light"], m["homo/mean/oracle/mae_fz_light_sd"] = 0.4321, 0.0123
    for pair, r2, sd in (("a_b", 0.3, 0.1), ("b_a", 0.05, 0.1)):       # b_a: above 0 by less than its sd
        for a in ("fx", "fy", "fz"):
            m[f"hetero/{pair}/genforce_comp/r2_{a}"], m[f"hetero/{pair}/genforce_comp/r2_{a}_sd"] = r2, sd
        m[f"hetero/{pair}/source_only/mae_total"] = 1.0
        m[f"hetero/{pair}/genforce/mae_total"] = 0.5
    return m


def test_cells_are_mean_plus_minus_sd_and_counts_are_beyond_the_spread():
    t = force_table(_metrics(), "homo", "homo")
    assert "mean ± sd over the regressor seeds" in t["title"]
    fz = t["rows"][0]
    assert fz[0] == "MAE Fz (N), mean of 2 pairs"
    assert fz[2 + 1] == "1.23 ± 0.057" and fz[2 + 4] == "0.5"        # genforce, oracle columns
    light = next(r for r in t["rows"] if r[0] == "MAE Fz at light contact, 0.05-2 N (N), mean of 2 pairs")
    assert light[2 + 4] == "0.432 ± 0.012" and light[2 + 1] == "-"    # genforce has none here
    beats = next(r for r in t["rows"] if r[0] == "pairs where the method beats source-only (MAE)")
    assert beats[2 + 1] == "1/2"                                      # genforce: a_b only


def test_the_papers_targets_are_met_only_beyond_the_spread():
    rows = {r[0]: r for r in targets(_metrics())["rows"]}
    assert rows["homo: GenForce beats source-only on every pair"][1:] == ["1/2", "no"]
    assert rows["hetero: R2 > 0 on every axis with genforce_comp"][1:] == ["1/2", "no"]
    assert rows["hetero: GenForce beats source-only on every pair"][1:] == ["2/2", "yes"]   # no spread given
