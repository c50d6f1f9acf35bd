"""scripts/choose.py prints validation means only: no test-split metric reaches its table."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

import choose  # noqa: E402


def test_the_table_holds_the_validation_means_alone():
    metrics = {"homo/mean/genforce/mae_total": 1.0, "homo_val/mean/genforce/mae_total": 2.0,
               "homo_val/mean/oracle/mae_total": 0.5, "homo_val/A_B/genforce/mae_total": 9.0,
               "homo_val/mean/oracle/mae_total_sd": 0.1, "homo_val/mean/oracle/r2_fz_sd": 0.2,
               "homo_val/mean/m2m/fid": 30.0, "homo/mean/m2m/fid": 31.0, "homo_val/mean/genforce/r2_fz": 0.9,
               "hetero_val/mean/source_only/mae_total": 3.0, "material_val/mean/flow_warp/fid": 7.0}
    assert choose.validation(metrics, ["homo", "hetero"]) == {
        "homo_val/mean/genforce/mae_total": 2.0, "homo_val/mean/oracle/mae_total": 0.5,
        "homo_val/mean/oracle/mae_total_sd": 0.1,
        "homo_val/mean/m2m/fid": 30.0, "hetero_val/mean/source_only/mae_total": 3.0}
