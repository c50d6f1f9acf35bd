"""The sensor catalogue: studies' members and pairs, bodies, and what each node runs on."""
import pytest

from stages import catalogue as C

STUDIES = {"sim-m2m": {"pairs": "ring", "sensors": 0}, "homo": {"pairs": "star", "sensors": 0},
           "material": {"pairs": "star", "sensors": 3}, "hetero": {"pairs": "all", "sensors": 0}}
GEL = {"pad_mm": [25.0, 25.0], "material": "r10", "grid": [65, 65], "source": "render"}
SENSORS = {
    "pad": {"pad_mm": [20.0, 20.0], "material": "sim", "source": "render", "studies": []},
    "P1": {"pad_mm": [20.0, 20.0], "material": "sim", "source": "render", "body": "pad", "studies": ["sim-m2m"]},
    "P2": {"pad_mm": [20.0, 20.0], "material": "sim", "source": "render", "body": "pad", "studies": ["sim-m2m"]},
    "P3": {"pad_mm": [20.0, 20.0], "material": "sim", "source": "render", "body": "pad", "studies": ["sim-m2m"]},
    "r10": {**GEL, "studies": ["material"], "hardness": 10},
    "A2": {**GEL, "body": "r10", "studies": ["homo", "hetero"]},
    "A1": {**GEL, "body": "r10", "studies": ["homo"]},
    "C1": {**GEL, "body": "r10", "studies": ["homo"]},
    "r6": {**GEL, "material": "r6", "studies": ["material"], "hardness": 6},
    "r18": {**GEL, "material": "r18", "studies": ["material"], "hardness": 18},
    "r8": {**GEL, "material": "r8", "studies": ["material"], "hardness": 8},
    "tactip": {"pad_mm": [40.0, 40.0], "material": "tactip", "source": "render", "studies": ["hetero"]},
    "skin": {"pad_mm": [24.6, 22.6], "material": "uskin", "source": "taxels", "studies": []},
    "skin3": {"pad_mm": [24.6, 22.6], "material": "uskin", "source": "taxels", "body": "skin", "studies": ["hetero"]},
}


def test_pairs_by_rule_and_size():
    assert C.pairs(SENSORS, STUDIES, "sim-m2m") == [["P1", "P2"], ["P2", "P3"], ["P3", "P1"]]
    assert C.pairs(SENSORS, STUDIES, "homo") == [["A2", "A1"], ["A1", "A2"], ["A2", "C1"], ["C1", "A2"]]
    assert C.members(SENSORS, STUDIES, "material") == ["r10", "r6", "r18"]      # the first 3: r8 left out
    assert len(C.pairs(SENSORS, STUDIES, "hetero")) == 3 * 2
    assert C.pairs(SENSORS, {**STUDIES, "sim-m2m": {"pairs": "ring", "sensors": 2}}, "sim-m2m") == [["P1", "P2"]]
    assert C.pairs(SENSORS, {**STUDIES, "homo": {"pairs": "all", "sensors": 1}}, "homo") == []


def test_material_groups_by_hardness():
    g = C.groups(SENSORS, STUDIES, "material")
    assert g == {"hard_to_soft": [["r6", "r10"], ["r10", "r18"]],
                 "soft_to_hard": [["r10", "r6"], ["r18", "r10"]]}
    assert C.groups(SENSORS, STUDIES, "hetero") == {"pairs": C.pairs(SENSORS, STUDIES, "hetero")}
    broken = {**SENSORS, "r6": {**SENSORS["r6"], "hardness": "soft"}}
    with pytest.raises(C.CatalogueError, match=r"sensors.r6.hardness \(the elastomer's B:A ratio\) must be a number"):
        C.groups(broken, STUDIES, "material")


def test_what_each_node_runs_on():
    assert C.by_source(SENSORS, STUDIES, "render") == ["P1", "P2", "P3", "r10", "A2", "A1", "C1", "r6", "r18",
                                                       "tactip"]
    assert C.by_source(SENSORS, STUDIES, "taxels") == ["skin3"]
    assert C.bodies(SENSORS, STUDIES) == ["pad", "r10", "r6", "r18", "tactip", "skin"]
    assert C.bodies(SENSORS, STUDIES, force_only=True) == ["r10", "r6", "r18", "tactip", "skin"]
    assert C.force_sensors(SENSORS, STUDIES) == ["r10", "A2", "A1", "C1", "r6", "r18", "tactip", "skin3"]
    assert ["A2", "tactip"] in C.transfer_pairs(SENSORS, STUDIES)


def test_a_copied_sensor_joins_what_its_original_does():
    copy = {**SENSORS, "A9": dict(SENSORS["A2"])}
    assert C.members(copy, STUDIES, "homo")[-1] == "A9" and "A9" in C.members(copy, STUDIES, "hetero")
    assert ["A2", "A9"] in C.pairs(copy, STUDIES, "homo") and ["A9", "tactip"] in C.pairs(copy, STUDIES, "hetero")
    assert "A9" in C.by_source(copy, STUDIES, "render") and C.bodies(copy, STUDIES) == C.bodies(SENSORS, STUDIES)


@pytest.mark.parametrize("change, message", [
    ({"A1": {**SENSORS["A1"], "studies": ["homo", "hetro"]}}, r"sensors.A1.studies names \['hetro'\], not studies"),
    ({"A1": {**SENSORS["A1"], "body": "nosuch"}}, r"sensors.A1.body names 'nosuch', which is not a sensor"),
    ({"A1": {**SENSORS["A1"], "material": "r6"}}, r"sensors.A1 rides on body 'r10' but its material differ"),
    ({"A1": {**SENSORS["A1"], "source": "camera"}}, r"sensors.A1.source must be one of render, taxels, got 'camera'"),
])
def test_catalogue_errors_name_the_entry(change, message):
    with pytest.raises(C.CatalogueError, match=message):
        C.bodies({**SENSORS, **change}, STUDIES)
        C.by_source({**SENSORS, **change}, STUDIES, "render")
    assert C.CatalogueError.user_error is True


def test_study_rules_are_checked():
    with pytest.raises(C.CatalogueError, match=r"studies.homo.pairs must be one of ring, star, all, got 'pairs'"):
        C.pairs(SENSORS, {**STUDIES, "homo": {"pairs": "pairs"}}, "homo")
    with pytest.raises(C.CatalogueError, match=r"studies: no study 'nope'"):
        C.members(SENSORS, STUDIES, "nope")
