"""Where things sit in the GenForce authors' released dataset, and which sensors it holds.

Light on purpose (standard library only): the graph's Listing grids call `sensors` and
`calibrated_sensors` at plan time, on every verb, so they list folders and read nothing.

The tree, as the authors' loaders and scripts read it (SuhangXia/GenForce_Code):

  <data.root>/training/                          (or data.root itself when it holds the sets)
    homo/img/npy/<sensor>/<indenter>/<point>/NNNN.{npy,jpg}, last.csv
    homo/img/npy/<sensor>_ref.{npy,jpg}           beside the sensor folders
    homo/img/npy_csv/<sensor>/<indenter>/<point>/last.csv   read first where it exists
    homo/force/<sensor>/<indenter>/<point>/ft.csv
    modulus/{img,force,depth}/<sensor>/...        no `npy` level; depth: inc_z.csv, dec_z.csv
    hetero/{img,force,depth}/<sensor>/...
    material_compensation/hetero/cofficient/<sensor>_{down,up}.csv
    material_compensation/modulus/cofficients/modulus/<sensor>_{down,up}.csv   (their spelling)

A sensor is every folder under a set's image folder (the authors' own: SET_SENSORS); the
homo images fall back to homo/img when there is no npy level.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from stages.common import InputError

SOURCES = ("twin", "authors")
# the authors' sensors per set, in their scripts' order (m2m/m2m/m2m_{homo,modulus,heter}.sh)
SET_SENSORS = {
    "homo": ("Array-I", "Circle-I", "Diamond-I", "Array-II", "Circle-II"),
    "modulus": tuple(f"ratio_{k}" for k in range(6, 20, 2)),
    "hetero": ("gelsight", "uskin", "tactip"),
}
SETS = tuple(SET_SENSORS)
DEPTH_SETS = ("modulus", "hetero")
# the coefficient folders their README and yamls name, then spellings a re-packed copy may use
COEFFICIENT_DIRS = {
    "hetero": ("material_compensation/hetero/cofficient", "material_compensation/hetero/coefficient",
               "material_compensation/hetero/cofficients", "material_compensation/hetero"),
    "modulus": ("material_compensation/modulus/cofficients/modulus", "material_compensation/modulus/cofficients",
                "material_compensation/modulus/coefficients/modulus", "material_compensation/modulus/coefficients",
                "material_compensation/modulus"),
}
_GRID_VALUE = re.compile(r"^[^\[\],=\s{}]+$")     # what the engine accepts as a grid value


@dataclass(frozen=True)
class SensorDirs:
    """One sensor's folders: images, forces, depth (None: the homo set has none), where its
    last.csv files sit, and the folder holding `<sensor>_ref.*`."""
    sensor: str
    set: str
    images: Path
    force: Path
    depth: Path | None
    last_csv: Path
    reference_dir: Path


def training_root(root) -> Path:
    """The `training` folder under data.root (or data.root itself when it holds the sets)."""
    if root is None or str(root).strip() == "":
        raise InputError("data.source is 'authors' but data.root is not set: "
                         "-p data.root=DIR, the folder that holds training/")
    base = Path(os.path.expanduser(str(root)))
    if (base / "training").is_dir():
        return base / "training"
    if any((base / s).is_dir() for s in SETS):
        return base
    if not base.is_dir():
        raise InputError(f"data.root: no folder {base}")
    raise InputError(f"data.root: {base} holds neither training/ nor any of {', '.join(SETS)}/ "
                     "(the authors' dataset unzips into dataset/training/)")


def _subdirs(folder: Path) -> list[str]:
    try:
        return [e.name for e in os.scandir(folder) if e.is_dir() and not e.name.startswith(".")]
    except FileNotFoundError:
        return []


def _image_dir(training: Path, set_name: str) -> Path:
    img = training / set_name / "img"
    if set_name == "homo" and (img / "npy").is_dir():
        return img / "npy"
    return img


def _ordered(found: list[str], known: tuple[str, ...]) -> list[str]:
    """The authors' sensors in their order, then any other folder by name."""
    return [s for s in known if s in found] + sorted(s for s in found if s not in known)


def set_sensors(training: Path) -> dict[str, list[str]]:
    """{set: its sensors} for the sets present under `training` (image folders define them)."""
    out, seen = {}, {}
    for set_name in SETS:
        img = _image_dir(training, set_name)
        names = _ordered([n for n in _subdirs(img) if n != "npy_csv"], SET_SENSORS[set_name])
        for n in names:
            if not _GRID_VALUE.match(n):
                raise InputError(f"data.root: sensor folder {img / n} has a name the pipeline cannot "
                                 "use as an instance name (no spaces, brackets, commas, '=' or braces)")
            if n in seen:
                raise InputError(f"data.root: sensor {n!r} is in both the {seen[n]} and the {set_name} set "
                                 f"({img / n}); instance names must be unique")
            seen[n] = set_name
        if names:
            out[set_name] = names
    return out


def sensors(source: str, root) -> list[str]:
    """Listing for ingest[sensor]: every sensor of every set under data.root; [] for the twin."""
    if source not in SOURCES:
        raise InputError(f"data.source must be one of {', '.join(SOURCES)}, got {source!r}")
    if source == "twin":
        return []
    found = set_sensors(training_root(root))
    if not found:
        raise InputError(f"data.root: no sensor folders under {training_root(root)}/"
                         f"{{homo/img/npy,modulus/img,hetero/img}}/")
    return [s for names in found.values() for s in names]


def coefficient_dir(training: Path, set_name: str) -> Path | None:
    """The first of COEFFICIENT_DIRS[set_name] that holds a `*_down.csv`, or None."""
    for rel in COEFFICIENT_DIRS.get(set_name, ()):
        folder = training / rel
        try:
            if any(n.endswith("_down.csv") for n in os.listdir(folder)):
                return folder
        except (FileNotFoundError, NotADirectoryError):
            continue
    return None


def coefficient_files(training: Path, set_name: str) -> dict[str, tuple[Path, Path]]:
    """{sensor: (<sensor>_down.csv, <sensor>_up.csv)} of a set's material-compensation folder."""
    folder = coefficient_dir(training, set_name)
    if folder is None:
        return {}
    names = sorted(os.listdir(folder))
    out = {}
    for n in names:
        if not n.endswith("_down.csv"):
            continue
        sensor = n[:-len("_down.csv")]
        up = folder / f"{sensor}_up.csv"
        if not up.is_file():
            raise InputError(f"data.root: {folder / n} has no unloading partner {up}")
        out[sensor] = (folder / n, up)
    for n in names:
        if n.endswith("_up.csv") and n[:-len("_up.csv")] not in out:
            raise InputError(f"data.root: {folder / n} has no loading partner "
                             f"{folder / (n[:-len('_up.csv')] + '_down.csv')}")
    return out


def calibrated_sensors(source: str, root) -> list[str]:
    """Listing for authors_calibration[sensor]: the sensors with coefficient files (modulus,
    then hetero); [] for the twin."""
    if source not in SOURCES:
        raise InputError(f"data.source must be one of {', '.join(SOURCES)}, got {source!r}")
    if source == "twin":
        return []
    training = training_root(root)
    out: list[str] = []
    for set_name in DEPTH_SETS:
        files = coefficient_files(training, set_name)
        for s in _ordered(list(files), SET_SENSORS[set_name]):
            if not _GRID_VALUE.match(s):
                raise InputError(f"data.root: coefficient file {files[s][0]} names a sensor the "
                                 "pipeline cannot use as an instance name")
            if s in out:
                raise InputError(f"data.root: sensor {s!r} has coefficient files in two sets")
            out.append(s)
    return out


def locate(root, sensor: str) -> SensorDirs:
    """The folders of one sensor of the dataset under data.root."""
    training = training_root(root)
    for set_name, names in set_sensors(training).items():
        if sensor in names:
            img = _image_dir(training, set_name)
            csv_root = img.parent / "npy_csv" if img.name == "npy" else img
            return SensorDirs(sensor, set_name, img / sensor, training / set_name / "force" / sensor,
                              training / set_name / "depth" / sensor if set_name in DEPTH_SETS else None,
                              (csv_root if csv_root.is_dir() else img) / sensor, img)
    raise InputError(f"data.root: no sensor {sensor!r} under {training} (image folders of "
                     f"{', '.join(SETS)})")


def locate_coefficients(root, sensor: str) -> tuple[str, Path, Path]:
    """(set, <sensor>_down.csv, <sensor>_up.csv) of a sensor with material-compensation curves."""
    training = training_root(root)
    for set_name in DEPTH_SETS:
        files = coefficient_files(training, set_name)
        if sensor in files:
            return (set_name, *files[sensor])
    raise InputError(f"data.root: no {sensor}_down.csv / {sensor}_up.csv in the material-compensation "
                     f"folders under {training} ({', '.join(d for v in COEFFICIENT_DIRS.values() for d in v[:1])})")


def require_sensors(source: str, root, set_name: str, needed) -> list[str]:
    """The set's sensors, or an InputError naming the set's folder and the first sensor of
    `needed` it lacks (a study's wiring calls this at plan time: exit 2, nothing run)."""
    if set_name not in SETS:
        raise InputError(f"unknown set {set_name!r}; the authors' sets are {', '.join(SETS)}")
    if source != "authors":
        return []
    training = training_root(root)
    have = set_sensors(training).get(set_name, [])
    for s in needed:
        if s not in have:
            raise InputError(f"data.root: the {set_name} set has no sensor {s!r} "
                             f"(no folder {_image_dir(training, set_name) / s}; found: {', '.join(have) or 'none'})")
    return have


def ordered_pairs(source: str, root, set_name: str) -> list[list[str]]:
    """Every ordered pair [source, target] of a set's sensors (at least two needed); [] for
    the twin.  A Listing for a study's transfer grid."""
    if source != "authors":
        if source not in SOURCES:
            raise InputError(f"data.source must be one of {', '.join(SOURCES)}, got {source!r}")
        return []
    have = require_sensors(source, root, set_name, ())
    if len(have) < 2:
        raise InputError(f"data.root: the {set_name} set needs at least two sensors for a transfer "
                         f"study, found {', '.join(have) or 'none'} under {training_root(root)}")
    return [[a, b] for a in have for b in have if a != b]
