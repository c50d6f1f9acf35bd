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

Every function is a plan-time listing (pipeline.graph.Listing): plain Python, no heavy import.
"""
from __future__ import annotations

from typing import Mapping

STUDIES = ("sim-m2m", "homo", "material", "hetero")
FORCE_STUDIES = ("homo", "material", "hetero")   # the studies whose pairs train force models
PAIRINGS = ("ring", "star", "all")
SOURCES = ("render", "taxels")
# what a body is: a sensor on another's body must have these as that body has them
MECHANICS = ("pad_mm", "thickness_mm", "curvature_radius_mm", "material", "grid", "spacing_mm",
             "max_depth_mm", "trajectory", "depth_scale")


class CatalogueError(ValueError):
    """A catalogue entry or study setting the plan cannot use: one line, exit 2."""
    user_error = True


def members(sensors: Mapping, studies: Mapping, study: str) -> list[str]:
    """The sensors of `study`, in catalogue order, the first `studies[study].sensors` of them."""
    if study not in studies:
        raise CatalogueError(f"studies: no study {study!r} (known: {', '.join(studies)})")
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
    limit = int(studies[study].get("sensors", 0))
    return found[:limit] if limit > 0 else found


def pairs(sensors: Mapping, studies: Mapping, study: str) -> list[list[str]]:
    """The ordered (source, target) pairs of `study`, by its `pairs` rule."""
    names = members(sensors, studies, study)
    rule = studies[study].get("pairs", "all")
    if rule not in PAIRINGS:
        raise CatalogueError(f"studies.{study}.pairs must be one of {', '.join(PAIRINGS)}, got {rule!r}")
    if len(names) < 2:
        return []
    if rule == "ring":
        out = [[a, b] for a, b in zip(names, names[1:] + names[:1])]
        return out[:1] if len(names) == 2 else out
    if rule == "star":
        return [p for other in names[1:] for p in ([names[0], other], [other, names[0]])]
    return [[a, b] for a in names for b in names if a != b]


def groups(sensors: Mapping, studies: Mapping, study: str) -> dict[str, list[list[str]]]:
    """The study's pairs in its groups: the material study's hard_to_soft and soft_to_hard (by
    the sensors' `hardness`), one group `pairs` otherwise."""
    all_pairs = pairs(sensors, studies, study)
    if study != "material":
        return {"pairs": all_pairs}

    def hardness(name):
        value = sensors[name].get("hardness")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CatalogueError(f"sensors.{name}.hardness (the elastomer's B:A ratio) must be a number "
                                 f"for the material study, got {value!r}")
        return float(value)
    out = {"hard_to_soft": [], "soft_to_hard": []}
    for s, t in all_pairs:
        out["hard_to_soft" if hardness(s) < hardness(t) else "soft_to_hard"].append([s, t])
    return out


def transfer_pairs(sensors: Mapping, studies: Mapping) -> list[list[str]]:
    """Every pair a force study transfers, once."""
    out: list[list[str]] = []
    for study in FORCE_STUDIES:
        out += [p for p in pairs(sensors, studies, study) if p not in out]
    return out


def image_pairs(sensors: Mapping, studies: Mapping) -> list[list[str]]:
    """Every pair some study scores the images of: sim-m2m's and the force studies'."""
    out = pairs(sensors, studies, "sim-m2m") if "sim-m2m" in studies else []
    return out + [p for p in transfer_pairs(sensors, studies) if p not in out]


def active(sensors: Mapping, studies: Mapping, which=STUDIES) -> list[str]:
    """The sensors some study of `which` takes part with, in catalogue order."""
    used = {n for study in which if study in studies for n in members(sensors, studies, study)}
    return [n for n in sensors if n in used]


def by_source(sensors: Mapping, studies: Mapping, source: str) -> list[str]:
    """The active sensors whose raw signal comes from `source` (render: a camera image; taxels:
    magnetic signals)."""
    out = []
    for name in active(sensors, studies):
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


def bodies(sensors: Mapping, studies: Mapping, force_only: bool = False) -> list[str]:
    """The bodies of the active sensors (force_only: of the force studies' sensors), in
    catalogue order: what deform (calibrate) runs on."""
    names = active(sensors, studies, FORCE_STUDIES if force_only else STUDIES)
    used = {body(sensors, n) for n in names}
    return [n for n in sensors if n in used]


def force_sensors(sensors: Mapping, studies: Mapping) -> list[str]:
    """The sensors of the force studies: each gets its own regressor (source-only, oracle)."""
    return active(sensors, studies, FORCE_STUDIES)
