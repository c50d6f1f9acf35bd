"""Group means of the transfer studies (paper Fig. 5E-F: hard-to-soft and soft-to-hard)."""
import pytest

from stages.studies import group_means


def test_group_means_average_each_groups_pairs():
    metrics = {"material/r6_r10/genforce/mae_fz": 1.0, "material/r6_r18/genforce/mae_fz": 3.0,
               "material/r10_r6/genforce/mae_fz": 0.5, "material/r6_r10/oracle/r2_fz": 0.75,
               "material/mean/genforce/mae_fz": 1.5, "homo/r6_r10/genforce/mae_fz": 9.0}
    groups = {"hard_to_soft": [["r6", "r10"], ["r6", "r18"]], "soft_to_hard": [["r10", "r6"]]}
    out = group_means(metrics, "material", groups)
    assert out == {"material/hard_to_soft/genforce/mae_fz": pytest.approx(2.0),
                   "material/hard_to_soft/oracle/r2_fz": pytest.approx(0.75),
                   "material/soft_to_hard/genforce/mae_fz": pytest.approx(0.5)}
