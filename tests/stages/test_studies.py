"""Group means of the transfer studies (paper Fig. 5E-F: hard-to-soft and soft-to-hard)."""
import pytest

from stages.studies import group_means


def test_group_means_average_each_groups_pairs():
    metrics = {"material/r6_r10/genforce/mae_fz": 1.0, "material/r6_r18/genforce/mae_fz": 3.0,
               "material/r10_r6/genforce/mae_fz": 0.5, "material/r6_r10/oracle/r2_fz": 0.75,
               "material/mean/genforce/mae_fz": 1.5, "homo/r6_r10/genforce/mae_fz": 9.0}
    groups = {"hard_to_soft": [["r6", "r10"], ["r6", "r18"]], "soft_to_hard": [["r10", "r6"]]}
    metrics["material_val/r6_r18/genforce/mae_fz"] = 4.0          # the validation split, alike
    out = group_means(metrics, "material", groups)
    assert out == {"material/hard_to_soft/genforce/mae_fz": pytest.approx(2.0),
                   "material/hard_to_soft/oracle/r2_fz": pytest.approx(0.75),
                   "material/soft_to_hard/genforce/mae_fz": pytest.approx(0.5),
                   "material_val/hard_to_soft/genforce/mae_fz": pytest.approx(4.0)}


def test_transfer_study_keeps_its_parts_timings_out_of_the_content(monkeypatch):
    """image_study reports its seconds; in the study they belong to the provenance ("timing"),
    or every re-run would write a different artifact and never cut off downstream."""
    import stages.force.study as force_study_module
    import stages.m2m.study as m2m_nodes
    from stages.studies import transfer_study
    seen = {}

    def image_study(**kw):
        seen["image_pairs"], seen["markers"] = kw["pairs"], kw["markers"]
        return {"fid": [[1.0]], "figures": {"fid": b"png"}, "metrics": {"s/mean/m2m/fid": 2.0},
                "attrs": {"pairs": len(kw["pairs"])}, "timing": {"seconds": 4.25}}

    def force_study(**kw):
        seen["force_pairs"], seen["groups"] = kw["pairs"], kw["groups"]
        return {"mae": [[0.5]], "figures": {"radar": b"png"}, "metrics": {"s/a_b/genforce/mae_total": 0.5,
                                                                        "s/two/genforce/mae_total": 1.0,
                                                                        "s/two/genforce/mae_total_sd": 0.25},
                "attrs": {"study": "s"}}
    monkeypatch.setattr(m2m_nodes, "image_study", image_study)
    monkeypatch.setattr(force_study_module, "force_study", force_study)
    out = transfer_study(study="s", groups={"one": [["a", "b"]], "two": [["b", "a"], ["a", "b"]]},
                         features={}, translated={}, warped={}, own={}, transfer={}, markers={"a": "A"},
                         test_indenters=["x"], val_indenters=["y"], kid_subset=2, trace_frames=10)
    assert seen["image_pairs"] == [["a", "b"], ["b", "a"]]          # a pair in two groups, once
    assert seen["markers"] == {"a": "A"}                           # the motion errors' truth
    assert out["images"] == {"fid": [[1.0]]} and out["force"] == {"mae": [[0.5]]}
    assert out["timing"] == {"images": {"seconds": 4.25}}
    assert out["figures"] == {"images_fid": b"png", "force_radar": b"png"}
    # the force metrics' group rows come from force_study, with their seed spread (seed_statistics)
    assert seen["groups"] == {"one": [["a", "b"]], "two": [["b", "a"], ["a", "b"]]}
    assert out["metrics"]["s/two/genforce/mae_total_sd"] == 0.25 and "s/one/genforce/mae_total" not in out["metrics"]
