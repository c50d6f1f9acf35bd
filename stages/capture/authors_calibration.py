"""Node `authors_calibration[sensor]`: a sensor's material-compensation curves as the GenForce
authors released them, in the form stages.force.compensation reads.

`<sensor>_down.csv` and `<sensor>_up.csv` hold np.poly1d coefficients (highest power first) of
the normal-force magnitude |Fz| (N) against normalised depth.  Which is which, from their code:
  * force/com/com_hetero/data_loader.py and com_modulus/data_loader.py evaluate `_down` on the
    inc_z.csv depths and `_up` on dec_z.csv's, and multiply the labels by
    target(depth) / source(depth);
  * force/com/com_hetero/infer_force_correct.py picks `_down` where the predicted |Fz| rises
    (np.diff(-Fz) > 0) and `_up` where it falls, solving the curve for depth from |Fz|.
So `_down` is the loading curve (the indenter moving down, the force rising) and `_up` the
unloading one.  The curves take the depth as the ingested `normalised_depth`: the hetero
loader's per-sensor normalisation, the modulus files' values as they are (stages.capture.ingest).
stages.force.compensation.curves_from_calibration turns the artifact into Curves.
"""
from __future__ import annotations

from stages.capture.authors_files import read_coefficients
from stages.capture.authors_layout import locate_coefficients


def authors_calibration(*, root: str, sensor: str) -> dict:
    """loading_coefficients (the `_down` file) and unloading_coefficients (`_up`), float64, as
    np.loadtxt(f, delimiter=",") reads them; attrs: sensor, set, the two files."""
    set_name, down, up = locate_coefficients(root, sensor)
    return {"loading_coefficients": read_coefficients(down), "unloading_coefficients": read_coefficients(up),
            "attrs": {"sensor": sensor, "set": set_name, "loading_file": str(down), "unloading_file": str(up),
                      "depth": "normalised depth (ingest's normalised_depth)", "force": "|Fz| N"}}

