"""The sensor catalogue: which sensors each node and study runs, read from params.yaml `sensors`.

A sensor is one entry of `sensors` (its `extends` resolved by pipeline.params): its mechanics
(pad, elastomer, solver grid, trajectory), its look (marker pattern, camera or taxel drawing),
`body` (the entry whose pad and elastomer it rides on: sensors on one body share one
deformation; default: itself) and `studies` (the studies it takes part in).  `studies`
(params.yaml) says, per study, how its sensors pair up:

  pairs    ring   each sensor to the next, the last to the first (n pairs)
           star   the first sensor to every other and back (2 (n - 1) pairs)
           all    every ordered pair (n (n - 1) pairs)
  sensors  how many of its sensors take part, in catalogue order (0: all of them)

So a sensor copied under a new name joins everything its original does, and a profile sizes a
study without naming its sensors.  The material study's pairs go in two groups by the sensors'
`hardness` (the B:A ratio of the elastomer, higher = softer): hard_to_soft when the source is
the harder.

With `data.source: authors` (params `data`; every function takes data_source and data_root)
the studies homo, material and hetero run on the sensors of the authors' released homo,
modulus and hetero sets found under data.root (stages.capture.authors_layout), in the set's
order, every ordered pair of them (`sensors` still caps how many); a modulus sensor's hardness
is its ratio (ratio_6: 6).  Their data is the node `ingest[sensor]` instead of the twin's
`markers[skin]`, their calibration `authors_calibration[sensor]` (where the set has one)
instead of `calibrate[sensor=<body>]`: `sequences`, `sequence_node` and `calibrations` say which,
for the graph's inputs.  sim-m2m stays on the twin's patterns (the M2M's pretraining).

Every function is a plan-time listing (pipeline.graph.Listing): plain Python, no heavy import.
"""
from __future__ import annotations

import re
from typing import Mapping

from stages.capture import authors_layout

STUDIES = ("sim-m2m", "homo", "material", "hetero")
FORCE_STUDIES = ("homo", "material", "hetero")   # the studies whose pairs train force models
PAIRINGS = ("ring", "star", "all")
SOURCES = ("render", "taxels")
# what a body is: a sensor on another's body must have these as that body has them
MECHANICS = ("pad_mm", "thickness_mm", "curvature_radius_mm", "material", "grid", "spacing_mm",
             "max_depth_mm", "trajectory", "depth_scale", "shear_scale")
# the authors' set each force study runs on with data.source authors
AUTHORS_SETS = {"homo": "homo", "material": "modulus", "hetero": "hetero"}
_RATIO = re.compile(r"^ratio_(\d+(\.\d+)?)$")


class CatalogueError(ValueError):
    """A catalogue entry or study setting the plan cannot use: one line, exit 2."""
    user_error = True


def _authors(data_source) -> bool:
    if data_source not in authors_layout.SOURCES:
        raise CatalogueError(f"data.source must be one of {', '.join(authors_layout.SOURCES)}, got {data_source!r}")
    return data_source == "authors"


def from_authors(study: str, data_source="twin") -> bool:
    """Whether `study` runs on the authors' data (else on the twin's sensors)."""
    return _authors(data_source) and study in AUTHORS_SETS


def members(sensors: Mapping, studies: Mapping, study: str, data_source="twin", data_root=None,
            check: bool = False) -> list[str]:
    """The sensors of `study`, in catalogue order (the authors' set's order), the first
    `studies[study].sensors` of them.  check: with the authors' data, an error (one line) where
    the study's set has fewer than two sensors: the study's own param, which the engine raises
    only when a run needs the study."""
    if study not in studies:
        raise CatalogueError(f"studies: no study {study!r} (known: {', '.join(studies)})")
    limit = int(studies[study].get("sensors", 0))
    if from_authors(study, data_source):
        set_name = AUTHORS_SETS[study]
        if check:
            authors_layout.ordered_pairs(data_source, data_root, set_name)
        found = authors_layout.require_sensors(data_source, data_root, set_name, ())
        return found[:limit] if limit > 0 else found
    found = []
    for name, spec in sensors.items():
        tags = spec.get("studies", []) if isinstance(spec, Mapping) else []
        if not isinstance(tags, list):
            raise CatalogueError(f"sensors.{name}.studies must be a list of studies, got {tags!r}")
        unknown = [t for t in tags if t not in studies]
        if unknown:
            raise CatalogueError(f"sensors.{name}.studies names {unknown}, not studies ({', '.join(studies)})")
        if study in tags:
            found.append(name)
    return found[:limit] if limit > 0 else found


def pairs(sensors: Mapping, studies: Mapping, study: str, data_source="twin", data_root=None) -> list[list[str]]:
    """The ordered (source, target) pairs of `study`, by its `pairs` rule (the authors' data:
    every ordered pair)."""
    names = members(sensors, studies, study, data_source, data_root)
    rule = studies[study].get("pairs", "all")
    if rule not in PAIRINGS:
        raise CatalogueError(f"studies.{study}.pairs must be one of {', '.join(PAIRINGS)}, got {rule!r}")
    if from_authors(study, data_source):
        rule = "all"
    if len(names) < 2:
        return []
    if rule == "ring":
        out = [[a, b] for a, b in zip(names, names[1:] + names[:1])]
        return out[:1] if len(names) == 2 else out
    if rule == "star":
        return [p for other in names[1:] for p in ([names[0], other], [other, names[0]])]
    return [[a, b] for a in names for b in names if a != b]


def groups(sensors: Mapping, studies: Mapping, study: str, data_source="twin",
           data_root=None) -> dict[str, list[list[str]]]:
    """The study's pairs in its groups: the material study's hard_to_soft and soft_to_hard (by
    the sensors' `hardness`; the authors' ratio_K: K), one group `pairs` otherwise."""
    all_pairs = pairs(sensors, studies, study, data_source, data_root)
    if study != "material":
        return {"pairs": all_pairs}
    authors = from_authors(study, data_source)

    def hardness(name):
        if authors:
            m = _RATIO.match(name)
            if not m:
                raise CatalogueError(f"data.root: modulus sensor {name!r} is not named ratio_<B:A ratio>, "
                                     "so the material study cannot tell hard from soft")
            return float(m.group(1))
        value = sensors[name].get("hardness")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CatalogueError(f"sensors.{name}.hardness (the elastomer's B:A ratio) must be a number "
                                 f"for the material study, got {value!r}")
        return float(value)
    out = {"hard_to_soft": [], "soft_to_hard": []}
    for s, t in all_pairs:
        out["hard_to_soft" if hardness(s) < hardness(t) else "soft_to_hard"].append([s, t])
    return out


def transfer_pairs(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> list[list[str]]:
    """Every pair a force study transfers, once."""
    out: list[list[str]] = []
    for study in FORCE_STUDIES:
        out += [p for p in pairs(sensors, studies, study, data_source, data_root) if p not in out]
    return out


def image_pairs(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> list[list[str]]:
    """Every pair some study scores the images of: sim-m2m's and the force studies'."""
    out = pairs(sensors, studies, "sim-m2m") if "sim-m2m" in studies else []
    return out + [p for p in transfer_pairs(sensors, studies, data_source, data_root) if p not in out]


def active(sensors: Mapping, studies: Mapping, which=STUDIES, data_source="twin", data_root=None,
           twin_only: bool = False) -> list[str]:
    """The sensors some study of `which` takes part with: the twin's in catalogue order, then
    the authors' (data.source authors) in their sets' order.  twin_only: the twin's alone (what
    the simulation, rendering and segmentation nodes run on)."""
    twin = [s for s in which if s in studies and not from_authors(s, data_source)]
    used = {n for study in twin for n in members(sensors, studies, study)}
    out = [n for n in sensors if n in used]
    if twin_only:
        return out
    for study in which:
        if study in studies and from_authors(study, data_source):
            for n in members(sensors, studies, study, data_source, data_root):
                if n in used:
                    raise CatalogueError(f"sensor {n!r} is both a twin sensor of params `sensors` and a "
                                         f"sensor of the authors' data under data.root: rename the twin's")
                if n not in out:
                    out.append(n)
    return out


def by_source(sensors: Mapping, studies: Mapping, source: str, data_source="twin", data_root=None) -> list[str]:
    """The active twin sensors whose raw signal comes from `source` (render: a camera image;
    taxels: magnetic signals)."""
    out = []
    for name in active(sensors, studies, data_source=data_source, data_root=data_root, twin_only=True):
        got = sensors[name].get("source")
        if got not in SOURCES:
            raise CatalogueError(f"sensors.{name}.source must be one of {', '.join(SOURCES)}, got {got!r}")
        if got == source:
            out.append(name)
    return out


def body(sensors: Mapping, name: str) -> str:
    """The entry whose mechanics `name` rides on; its mechanics must be that entry's."""
    got = sensors[name].get("body") or name
    if got not in sensors:
        raise CatalogueError(f"sensors.{name}.body names {got!r}, which is not a sensor")
    differ = [k for k in MECHANICS if sensors[name].get(k) != sensors[got].get(k)]
    if differ:
        raise CatalogueError(f"sensors.{name} rides on body {got!r} but its {', '.join(differ)} differ from "
                             f"the body's: give it its own body (drop `body`) or the body's values")
    return str(got)


def bodies(sensors: Mapping, studies: Mapping, force_only: bool = False, data_source="twin",
           data_root=None) -> list[str]:
    """The bodies of the active twin sensors (force_only: of the force studies' sensors), in
    catalogue order: what deform (calibrate) runs on."""
    names = active(sensors, studies, FORCE_STUDIES if force_only else STUDIES, data_source, data_root,
                   twin_only=True)
    used = {body(sensors, n) for n in names}
    return [n for n in sensors if n in used]


def force_sensors(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> list[str]:
    """The sensors of the force studies: each gets its own regressor (source-only, oracle)."""
    return active(sensors, studies, FORCE_STUDIES, data_source, data_root)


TWIN_M2M = "twin"   # the one M2M fine-tune of the twin's force sensors


def m2m_members(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> dict[str, list[str]]:
    """{M2M fine-tune: the sensors it pairs frames among}.  On the twin, whose sensors all
    follow one trajectory, one ("twin") of all the force studies' sensors; on the authors'
    data, one per set, named by it, whose sensors were collected along the same contacts (the
    authors fine-tune one M2M per set: a contact number of one set is no location of
    another's), so a set's bad data stops only the studies that read it."""
    if not _authors(data_source):
        return {TWIN_M2M: force_sensors(sensors, studies, data_source, data_root)}
    out: dict[str, list[str]] = {}
    for study in FORCE_STUDIES:
        taken = {n for g in out.values() for n in g}
        group = [n for n in members(sensors, studies, study, data_source, data_root) if n not in taken]
        if len(group) > 1:
            out[AUTHORS_SETS[study]] = group
    return out


def m2m_fits(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> list[str]:
    """The grid of the m2m node: its fine-tunes' names (m2m_members)."""
    return list(m2m_members(sensors, studies, data_source, data_root))


def m2m_of(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> dict[str, str]:
    """{sensor: the m2m instance whose fine-tune holds it}, for translate's model input."""
    return {n: f"m2m[fit={fit}]" for fit, names in m2m_members(sensors, studies, data_source, data_root).items()
            for n in names}


# -- which node holds a sensor's data: the graph's Wiring params ------------------------------

def sequences(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> dict[str, str]:
    """{sensor: the instance holding its contact sequence} for every active sensor: the twin's
    `markers[skin=...]`, the authors' `ingest[sensor=...]`."""
    twin = set(active(sensors, studies, data_source=data_source, data_root=data_root, twin_only=True))
    return {n: f"markers[skin={n}]" if n in twin else f"ingest[sensor={n}]"
            for n in active(sensors, studies, data_source=data_source, data_root=data_root)}


def sequence_node(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> dict[str, str]:
    """The node and grid variable holding the force studies' sequences, for gathers
    ("{seqs[node]}[{seqs[var]}=@members]")."""
    authors = any(from_authors(s, data_source) for s in FORCE_STUDIES if s in studies)
    return {"node": "ingest", "var": "sensor"} if authors else {"node": "markers", "var": "skin"}


def calibrations(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> dict[str, str]:
    """{sensor: the instance holding its material calibration, or "" where it has none} for
    every force-study sensor: the twin's `calibrate[sensor=<its body>]`, the authors'
    `authors_calibration[sensor=...]` where data.root holds its coefficient files."""
    twin = set(active(sensors, studies, FORCE_STUDIES, data_source, data_root, twin_only=True))
    calibrated = set(authors_layout.calibrated_sensors(data_source, data_root)) if _authors(data_source) else set()
    out = {}
    for n in force_sensors(sensors, studies, data_source, data_root):
        if n in twin:
            out[n] = f"calibrate[sensor={body(sensors, n)}]"
        else:
            out[n] = f"authors_calibration[sensor={n}]" if n in calibrated else ""
    return out


def punch_calibrations(sensors: Mapping, studies: Mapping, data_source="twin", data_root=None) -> dict[str, str]:
    """{sensor: its flat-punch calibration, or "" where it has none} for every force-study
    sensor: the twin's `calibrate_punch[sensor=<its body>]`; the authors' sensors have none."""
    twin = set(active(sensors, studies, FORCE_STUDIES, data_source, data_root, twin_only=True))
    return {n: f"calibrate_punch[sensor={body(sensors, n)}]" if n in twin else ""
            for n in force_sensors(sensors, studies, data_source, data_root)}


def twin_data(data_source="twin") -> dict:
    """{} for the twin's data; with the authors' an error, for a node that runs the twin's
    sensors alone (raised only when a run needs that node)."""
    if _authors(data_source):
        raise CatalogueError("this node runs on the twin's sensors, and with data.source authors the "
                             "studies run on the authors' sensors instead: run it with data.source twin")
    return {}


def first_seed(seeds) -> list:
    """[the first regressor seed of force.seeds]: the models node `control` drives the gripper with."""
    return [seeds[0]]
