"""A tiny dataset in exactly the GenForce authors' released layout, written from their code's
facts (not with our reader's help), and what it holds, for the tests to compare against.

  training/<set>/img[/npy]/<sensor>/<indenter>/<point>/NNNN.npy   np.save(np.packbits(mask))
      (or NNNN.jpg: PIL writes the 0/255 mask), last.csv: np.savetxt of four full paths
  training/<set>/img[/npy]/<sensor>_ref.npy                        beside the sensor folders
  training/<set>/force/<sensor>/<indenter>/<point>/ft.csv          Fx(N),...,Tz(Nmm) header
  training/<set>/depth/<sensor>/<indenter>/<point>/{inc_z,dec_z}.csv   no header (not homo)
  training/material_compensation/hetero/cofficient/<sensor>_{down,up}.csv
  training/material_compensation/modulus/cofficients/modulus/<sensor>_{down,up}.csv

Each contact's four motions get their own frame counts (sensor, indenter and point decide
them), so frame numbers never line up across sensors: only last.csv's positions do.
"""
from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

H, W = 480, 640
FT_HEADER = "Fx(N),Fy(N),Fz(N),Tx(Nmm),Ty(Nmm),Tz(Nmm)"
IMG = {"homo": "homo/img/npy", "modulus": "modulus/img", "hetero": "hetero/img"}
COEFF = {"hetero": "material_compensation/hetero/cofficient",
         "modulus": "material_compensation/modulus/cofficients/modulus"}
# the hetero loader's z range per sensor (top, bottom); the fixture presses from top to bottom
HETERO_Z = {"gelsight": (1.12310475, -0.07459319), "tactip": (4.648126681, -0.049249177),
            "uskin": (1.08649, -0.0736)}
MAX_SHIFT = 17
_GRIDS: dict[int, np.ndarray] = {}


def _seed(*parts) -> int:
    return zlib.crc32("/".join(map(str, parts)).encode())


def mask(sensor: str, indenter: str, point: int, k: int) -> np.ndarray:
    """(480, 640) 0/1: square markers on a grid, moved by the frame (k = -1: the reference)."""
    shift = 0 if k < 0 else (k * 3 + point + len(indenter)) % MAX_SHIFT
    pitch = 24 + _seed(sensor) % 8
    if pitch not in _GRIDS:
        yy, xx = np.mgrid[0:H + MAX_SHIFT, 0:W + 2 * MAX_SHIFT]
        _GRIDS[pitch] = ((yy % pitch < 6) & (xx % pitch < 6)).astype(np.uint8)
    return _GRIDS[pitch][shift:shift + H, 2 * shift:2 * shift + W].copy()


def motion_lengths(sensor: str, indenter: str, point: int) -> list[int]:
    rng = np.random.default_rng(_seed(sensor, indenter, point))
    return [int(v) for v in rng.integers(2, 5, 4)]


def write_sensor(training: Path, set_name: str, sensor: str, indenters, points, *, jpg=False, crlf=False,
                 depth=True) -> list[dict]:
    """Write one sensor; return its contacts in folder order: indenter (folder name), point,
    lengths, ends, force (n,3) N, torque (n,3) N mm, inc, dec, n, suffix."""
    img_root = training / IMG[set_name]
    eol = "\r\n" if crlf else "\n"
    suffix = ".jpg" if jpg else ".npy"
    _save_frame(img_root / f"{sensor}_ref{suffix}", mask(sensor, "", 0, -1))
    out = []
    for ind in indenters:
        for point in points:
            lengths = motion_lengths(sensor, ind, point)
            n = sum(lengths)
            ends = list(np.cumsum(lengths) - 1)
            folder = img_root / sensor / ind / str(point)
            folder.mkdir(parents=True, exist_ok=True)
            for k in range(n):
                _save_frame(folder / f"{k:04d}{suffix}", mask(sensor, ind, point, k))
            # marker_seg/homo/homo.py: np.savetxt(last.csv, [paths], fmt="%s", delimiter=",")
            names = [f"/GenForce/dataset/{set_name}/image/npy/{sensor}/{ind}/{point}/{e:04d}{suffix}" for e in ends]
            np.savetxt(folder / "last.csv", names, fmt="%s", delimiter=",", newline=eol)
            rng = np.random.default_rng(_seed("ft", sensor, ind, point))
            force = np.round(rng.normal(0, 1, (n, 3)), 6)
            force[:, 2] = -np.abs(force[:, 2])
            torque = np.round(rng.normal(0, 30, (n, 3)), 4)          # N mm, the recorder's unit
            ft_dir = training / set_name / "force" / sensor / ind / str(point)
            ft_dir.mkdir(parents=True, exist_ok=True)
            rows = [",".join(repr(float(v)) for v in row) for row in np.c_[force, torque]]
            (ft_dir / "ft.csv").write_bytes((eol.join([FT_HEADER, *rows]) + eol).encode())
            c = {"indenter": ind, "point": point, "lengths": lengths, "ends": ends, "n": n, "force": force,
                 "torque": torque, "suffix": suffix, "inc": None, "dec": None}
            if set_name != "homo" and depth:
                c["inc"], c["dec"] = _depth(set_name, sensor, lengths)
                d_dir = training / set_name / "depth" / sensor / ind / str(point)
                d_dir.mkdir(parents=True, exist_ok=True)
                np.savetxt(d_dir / "inc_z.csv", c["inc"], delimiter=",", newline=eol)
                np.savetxt(d_dir / "dec_z.csv", c["dec"], delimiter=",", newline=eol)
            out.append(c)
    return out


def _depth(set_name, sensor, lengths):
    """inc_z: press and shear out; dec_z: shear back and release (one split the loader allows)."""
    p, s1, s2, r = lengths
    press = np.linspace(0, 1, p + 1)[1:]
    release = np.linspace(1, 0, r + 1)[1:]
    frac = np.r_[press, np.ones(s1 + s2), release]
    if set_name == "hetero":
        top, bottom = HETERO_Z.get(sensor, (2.0, -0.5))
        values = top - frac * (top - bottom)
    else:
        values = frac
    values = np.round(values, 8)
    return values[:p + s1], values[p + s1:]


def _save_frame(path: Path, m: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".npy":
        np.save(path, np.packbits(m))                   # homo.py: packbits of the whole mask
    else:
        from PIL import Image
        Image.fromarray((m * 255).astype(np.uint8)).save(path)


def write_coefficients(training: Path, set_name: str, sensor: str) -> tuple[np.ndarray, np.ndarray]:
    """<sensor>_down.csv and _up.csv: cubic coefficients, highest power first, one line each."""
    rng = np.random.default_rng(_seed("coef", sensor))
    down = np.r_[rng.uniform(-1, 1, 2), rng.uniform(1, 5), rng.uniform(-0.05, 0.05)]
    up = np.r_[rng.uniform(-1, 1, 2), rng.uniform(0.5, 4), rng.uniform(-0.05, 0.05)]
    folder = training / COEFF[set_name]
    folder.mkdir(parents=True, exist_ok=True)
    np.savetxt(folder / f"{sensor}_down.csv", down[None], delimiter=",")
    np.savetxt(folder / f"{sensor}_up.csv", up[None], delimiter=",")
    return down, up


DEFAULT = {
    "homo": {"Array-I": {}, "Array-II": {"jpg": True}},
    "modulus": {"ratio_6": {"crlf": True}, "ratio_8": {}},
    "hetero": {"gelsight": {}, "tactip": {}},
}
INDENTERS = {"homo": ("cone", "sphere_s", "wave"), "modulus": ("cone", "sphere-s", "wave"),
             "hetero": ("cone", "sphere_s", "wave")}
POINTS = (2, 10)           # sorted as integers: 2 before 10


def write_dataset(root: Path, sets=DEFAULT, indenters=INDENTERS, points=POINTS) -> dict:
    """Write dataset/training/... under root; return {sensor: {"set", "contacts", "coefficients"}}."""
    training = Path(root) / "training"
    truth = {}
    for set_name, sensors in sets.items():
        for sensor, opts in sensors.items():
            truth[sensor] = {"set": set_name,
                             "contacts": write_sensor(training, set_name, sensor, indenters[set_name], points, **opts)}
            if set_name in COEFF:
                truth[sensor]["coefficients"] = write_coefficients(training, set_name, sensor)
    return truth
