"""Gripper twin, grasp controller and slip avoider, with an oracle force predictor."""
import sys
import zlib

import numpy as np
import pytest
from scipy import ndimage

from stages.control.controller import GraspController, OraclePredictor, SlipAvoider
from stages.control.episodes import grasp_metrics, run_episode, slip_metrics
from stages.control.gripper import GripperTwin
from stages.control.nodes import control_study, oracle_factory, run_study
from stages.control.objects import DEFAULT_OBJECTS, grasp_object, profile_height
from stages.markers.patterns import gelsight_pattern, rasterize
from stages.sim.contact import solve_contact

PNG = b"\x89PNG\r\n\x1a\n"
# the GelSight twin's gel (params.yaml sensors.gelsight-r10 / materials.r10), pinned here
SENSOR = {"pad_mm": [25.0, 25.0], "thickness_mm": 4.0, "curvature_radius_mm": 0.0, "material": "r10",
          "grid": [65, 65], "spacing_mm": 0.390625, "max_depth_mm": 1.4}
MATERIAL = {"E": 5.2e5, "nu": 0.45, "mu": 0.55, "hysteresis": 0.12}
TWIN = {"grid": [33, 33]}
SIZE = (96, 96)


def obj(name):
    return grasp_object(name, DEFAULT_OBJECTS[name])


def oracle(**kw):
    return lambda twin: OraclePredictor(lambda: twin.true_force("left"), **kw)


def episode(name, make=None, **kw):
    return run_episode(obj(name), make or oracle(), sensor=SENSOR, material=MATERIAL, size=SIZE,
                       twin={**TWIN, **kw.pop("twin", {})}, **kw)


class FakeGripper:
    def __init__(self, width):
        self.w, self.moves, self.stops = width, [], 0

    def width(self):
        return self.w

    def move(self, width_m, speed_m_s):
        self.moves.append((width_m, speed_m_s))

    def stop(self):
        self.stops += 1


# -- controllers on their own -----------------------------------------------------------------

def test_grasp_controller_closes_then_p_controls_at_10_hz():
    c = GraspController(0.8)
    g = FakeGripper(0.030)
    c.start(0.0, g)
    assert g.moves == [(0.0, 0.005)]                          # close at the paper's 5 mm/s
    assert c.update(0.0, (0, 0, -0.05), g) is None            # below the contact threshold
    assert c.update(0.05, (0, 0, -0.5), g) is None            # between two 10 Hz ticks
    assert c.update(0.1, (0, 0, -0.5), g) == "contact"
    assert g.moves[-1] == pytest.approx((0.030 - 0.0004 * (0.8 - 0.5), 0.005))
    c.update(0.2, (0, 0, -1.3), g)                            # over target: opens
    assert g.moves[-1][0] == pytest.approx(0.030 + 0.0004 * 0.5)
    c.hold(g)
    assert g.stops == 1 and c.update(0.3, (0, 0, 0.0), g) is None
    with pytest.raises(ValueError, match="contact threshold"):
        GraspController(0.05)


def test_slip_avoider_threshold_over_three_samples():
    a = SlipAvoider()
    g = FakeGripper(0.020)
    a.start(0.0)
    fy = [0.5, 0.55, 0.6, 0.79, 0.89]                        # 3-sample variations 0.1, 0.24, 0.29
    hits = [a.update(k * 0.05, (0.0, f, -1.0), g) for k, f in enumerate(fy)]
    assert not any(hits) and g.moves == []
    assert a.update(0.25, (0.0, 1.10, -1.0), g)               # 1.10 - 0.79 = 0.31 > 0.3
    assert g.moves == [(pytest.approx(0.019), 0.015)]         # tighten 1 mm at 15 mm/s
    assert a.detections == [0.25]
    # busy while tightening (1 mm / 15 mm/s), then three fresh samples are needed again
    assert not a.update(0.30, (0.0, 2.0, -1.0), g)
    assert not a.update(0.35, (0.0, 0.0, -1.0), g) and not a.update(0.40, (0.0, 0.0, -1.0), g)
    assert a.update(0.45, (-0.4, 0.0, -1.0), g)               # Fx counts as well
    assert len(a.history) == 0


def test_oracle_noise_lag_and_gain():
    values = iter([np.array([0.0, 0.0, -float(k)]) for k in range(10)])
    p = OraclePredictor(lambda: next(values), lag_frames=2, gain=0.5)
    out = [p.step(None)[2] for _ in range(5)]
    assert out == [0.0, 0.0, 0.0, -0.5, -1.0]
    noisy = OraclePredictor(lambda: np.zeros(3), noise_N=0.1, seed=3)
    first = np.array([noisy.step(None) for _ in range(400)])
    noisy.reset()
    assert np.array_equal(noisy.step(None), first[0])         # reset replays the noise
    assert first.std() == pytest.approx(0.1, rel=0.1)


# -- the twin -----------------------------------------------------------------------------------

def test_twin_steady_force_matches_the_contact_solver():
    """Plum, closure 1 mm: the series chain 2 d + F(d) (2 / k_f + 1 / k_o) = 1 mm solved by
    bisection on direct contact solves gives the twin's force."""
    plum = obj("plum")
    twin = GripperTwin(plum, sensor=SENSOR, material=MATERIAL, grid=(33, 33),
                       width_m=(plum.width_mm - 1.0) * 1e-3)
    height = profile_height(plum, twin.shape, twin.spacing)
    compliance = 2 / 4.0 + 1 / plum.stiffness_N_mm
    lo, hi = 0.0, 0.5
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        force = -solve_contact(height, mid, **twin.solver).force[2]
        lo, hi = (lo, mid) if 2 * mid + force * compliance > 1.0 else (mid, hi)
    assert twin.normal_N == pytest.approx(force, rel=0.005)
    assert -twin.true_force()[2] == pytest.approx(force, rel=0.005)
    assert -twin.true_force()[2] == pytest.approx(0.5595, abs=2e-3)         # golden
    assert twin.gel_mm == pytest.approx(mid, rel=0.005)
    # the other finger feels the same normal force, its x axis mirrored
    assert twin.true_force("right")[2] == twin.true_force("left")[2]


def test_twin_no_contact_reads_the_reference():
    grape = obj("grape")
    twin = GripperTwin(grape, sensor=SENSOR, material=MATERIAL, grid=(33, 33), size=SIZE)
    ref = rasterize(gelsight_pattern("A-II"), size=SIZE)
    images = twin.read_sensors()
    assert set(images) == {"left", "right"}
    assert np.array_equal(images["left"], ref) and np.array_equal(twin.reference, ref)
    assert np.array_equal(twin.true_force(), np.zeros(3))
    twin.move(0.0, 0.005)
    twin.step(1.3)                                            # 3 mm approach at 5 mm/s + 3.5 mm
    assert twin.width() == pytest.approx((grape.width_mm - 3.5) * 1e-3)
    assert twin.normal_N > 1.0 and (twin.read_sensors()["left"] != ref).sum() > 10


def _centroids(image):
    labels, n = ndimage.label(image > 0)
    return np.array(ndimage.center_of_mass(image > 0, labels, range(1, n + 1)))[:, ::-1]  # (x, y)


def _marker_shift(before, after):
    """Per-marker centroid motion (x, y) px, markers matched to their nearest neighbour."""
    a, b = _centroids(before), _centroids(after)
    nearest = np.argmin(((a[:, None] - b[None]) ** 2).sum(-1), axis=1)
    return b[nearest] - a


@pytest.mark.parametrize("load, axis", [((0.0, 0.8), 1), ((0.8, 0.0), 0)])
def test_marker_images_shift_with_the_shear(load, axis):
    plum = obj("plum")
    kw = dict(sensor=SENSOR, material=MATERIAL, grid=(33, 33), size=(128, 128),
              width_m=(plum.width_mm - 1.5) * 1e-3)
    pressed = GripperTwin(plum, **kw)
    sheared = GripperTwin(plum, load=lambda t: np.array(load), **kw)
    sheared.step(0.05)
    assert not sheared.sliding
    assert sheared.true_force()[axis] == pytest.approx(0.4)                 # half on each pad
    assert sheared.true_force("right")[0] == pytest.approx(-sheared.true_force()[0])
    for finger, sign in (("left", 1.0), ("right", -1.0 if axis == 0 else 1.0)):
        shift = _marker_shift(pressed.read_sensors()[finger], sheared.read_sensors()[finger])
        moved = np.abs(shift).max(1) > 0
        assert moved.sum() >= 4                                           # near the contact
        along, across = sign * shift[moved, axis].mean(), abs(shift[moved, 1 - axis].mean())
        assert along > 0.15 and across < 0.2 * along                      # px; ~0.1 mm at 0.4 N


def test_sheared_solve_without_tangential_force_keeps_the_pressed_frame(monkeypatch):
    """A sheared solve whose contact carries no tangential force (it has let go: nothing to
    scale to the shear load) leaves the frame pressed-only instead of dividing by zero."""
    import dataclasses

    import stages.control.gripper as gripper_module
    plum = obj("plum")
    kw = dict(sensor=SENSOR, material=MATERIAL, grid=(33, 33), size=SIZE,
              width_m=(plum.width_mm - 1.5) * 1e-3)
    pressed = GripperTwin(plum, **kw)
    real = gripper_module.solve_contact

    def let_go(height, depth, shift=(0.0, 0.0), **solver):
        out = real(height, depth, shift=shift, **solver)
        return dataclasses.replace(out, force=np.zeros(3)) if any(shift) else out

    sheared = GripperTwin(plum, load=lambda t: np.array([0.0, 0.8]), **kw)
    monkeypatch.setattr(gripper_module, "solve_contact", let_go)   # after the stiffness table
    sheared.step(0.05)
    np.testing.assert_array_equal(sheared.read_sensors()["left"], pressed.read_sensors()["left"])
    assert sheared.true_force()[2] == pytest.approx(pressed.true_force()[2]) and sheared.true_force()[2] < 0


# -- closed loop --------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["strawberry", "wood_block"])     # 0.4 N/mm ... 80 N/mm
def test_grasp_reaches_the_target_force(name):
    ep = episode(name, grasp_s=3.5)
    m = grasp_metrics(ep, tolerance_N=0.25)
    assert m["force_error_N"] < 0.05 and m["success"] == 1.0 and m["crushed"] == 0.0
    assert ep["events"]["contact"].size == 1
    # a noisy, lagging estimate still holds the target within the tolerance
    ep = episode(name, oracle(noise_N=0.03, lag_frames=1, seed=1), grasp_s=3.5)
    assert grasp_metrics(ep, tolerance_N=0.25)["force_error_N"] < 0.1


def test_fragile_object_is_not_crushed_unless_the_force_is_under_read():
    chip = obj("potato_chip")
    ep = episode("potato_chip", grasp_s=2.5)
    assert not ep["crushed"] and ep["max_normal_N"] < chip.target_N + 0.1 < chip.crush_N
    # a model reading a tenth of the force squeezes towards 6 N, past the 2.5 N crush force
    ep = episode("potato_chip", oracle(gain=0.1), grasp_s=2.5)
    m = grasp_metrics(ep, tolerance_N=0.25)
    assert ep["crushed"] and m["crushed"] == 1.0 and m["success"] == 0.0
    assert ep["max_normal_N"] > chip.crush_N


PULL = {"start_s": 0.5, "rate_N_s": 8.0, "max_N": 1.5, "direction_deg": 90.0, "monitor_s": 2.5}


def test_slip_is_detected_within_the_window_and_stopped():
    ep = episode("banana", grasp_s=2.5, pull=PULL)
    m = slip_metrics(ep)
    assert ep["onset"] is not None and ep["onset"] > ep["marks"]["pull"]
    assert m["detected"] == 1.0 and 0.0 <= m["detected_s"] <= 0.5
    assert 0.05 < m["slip_mm"] < 1.0 and m["success"] == 1.0 and m["false_alarms"] == 0.0
    slip = np.hypot(*ep["slip_mm"].T)
    assert slip[-1] - slip[-20] < 1e-6                               # stopped
    # without the avoider the same pull drags the object out of the grasp
    passive = episode("banana", grasp_s=2.5, pull=PULL, controller={"threshold_N": np.inf})
    assert passive["dropped"] and slip_metrics(passive)["success"] == 0.0


def test_pull_below_friction_no_slip_no_false_detection():
    gentle = {**PULL, "rate_N_s": 1.0, "max_N": 0.3}
    ep = episode("plum", grasp_s=2.5, pull=gentle)
    m = slip_metrics(ep)
    assert ep["onset"] is None and "detected_s" not in m
    assert m["slip_mm"] == 0.0 and m["detected"] == 0.0 and m["tightenings"] == 0.0
    assert m["success"] == 1.0
    assert ep["force_true"][-1, 1] == pytest.approx(0.5 * (obj("plum").weight_N + 0.3))


# -- the node ---------------------------------------------------------------------------------

def test_study_outputs_and_metric_names():
    kw = dict(objects=DEFAULT_OBJECTS, grasp=["grape"], slip=["glue_stick"], sensor=SENSOR,
              material=MATERIAL, size=(64, 64), duration_s=2.0, pull={**PULL, "monitor_s": 1.5},
              twin=TWIN)
    out = run_study(oracle_factory(), **kw)
    n = out["grasp"]["grape"]["time"].size
    assert n == int(round((0.5 + 0.25 + 2.0) * 20)) + 1              # warm-up, tare, grasp
    assert out["grasp"]["grape"]["force_pred"].shape == (n, 3)
    assert out["grasp"]["grape"]["force_pred"].dtype == np.float32
    assert set(out["slip"]["glue_stick"]["events"]) == {"contact", "detected"}
    assert {"grasp_grape", "slip_glue_stick", "images"} <= set(out["figures"])
    assert all(bytes(v[:8]) == PNG for v in out["figures"].values())
    metrics = out["metrics"]
    for key in ("force_error_N", "crushed", "success", "pred_error_N"):
        assert f"control/grasp/grape/{key}" in metrics and f"control/mean/grasp/{key}" in metrics
    for key in ("detected_s", "slip_mm", "slip_mm_passive", "success"):
        assert f"control/slip/glue_stick/{key}" in metrics
    assert metrics["control/grasp/grape/success"] == 1.0
    assert metrics["control/slip/glue_stick/slip_mm_passive"] > 5.0
    assert out["attrs"]["targets_N"] == {"grape": 0.6, "glue_stick": 1.2}
    oracle_node = control_study(model=None, seed=0, **kw)
    assert oracle_node["attrs"]["predictor"] == "oracle"
    assert oracle_node["metrics"] == metrics
    with pytest.raises(KeyError, match="unicorn"):
        run_study(oracle_factory(), **{**kw, "grasp": ["unicorn"]})
    with pytest.raises(KeyError, match="speed"):
        run_study(oracle_factory(), **{**kw, "twin": {"speed": 1}})


class ConstantPredictor:
    """Reads a fixed force whatever it sees; remembers the reference it was reset with."""

    def __init__(self, force):
        self.force, self.references = np.asarray(force, np.float32), []

    def reset(self, reference=None):
        self.references.append(reference)

    def step(self, image):
        return self.force


def test_study_node_loads_the_model_artifact(monkeypatch):
    torch = pytest.importorskip("torch")
    predictor, calls = ConstantPredictor((0.0, 0.0, -2.0)), []

    def load_predictor(artifact, prefix="genforce_comp"):
        calls.append((artifact, prefix))
        return predictor

    fake = type(sys)("stages.force.model")
    fake.load_predictor = load_predictor
    monkeypatch.setitem(sys.modules, "stages.force.model", fake)
    threads = torch.get_num_threads()
    artifact = {"genforce_plus/weights": np.zeros(3)}
    out = control_study(model=artifact, objects=DEFAULT_OBJECTS, grasp=["potato_chip"], slip=[],
                        sensor=SENSOR, material=MATERIAL, size=(64, 64), duration_s=2.0, pull={},
                        seed=0, twin=TWIN)
    assert calls == [(artifact, "genforce_plus")] and out["attrs"]["predictor"] == "genforce_plus"
    assert torch.get_num_threads() == threads
    assert predictor.references[0].shape == (64, 64)           # the twin's no-contact image
    # a model stuck at 2 N (tared to 0 before contact) never feels the chip and crushes it
    assert out["metrics"]["control/grasp/potato_chip/crushed"] == 1.0
    assert out["grasp"]["potato_chip"]["events"]["contact"].size == 0


class ContactPredictor:
    """Reads -gain N per 1% of the image's pixels that differ from the reference."""

    def __init__(self, gain):
        self.gain = gain

    def reset(self, reference=None):
        self.reference = reference

    def step(self, image):
        return np.array([0.0, 0.0, -self.gain * 100 * np.mean(image != self.reference)], np.float32)


def test_catalogue_entries_are_checked():
    entry = dict(DEFAULT_OBJECTS["grape"])
    del entry["mu"]
    with pytest.raises(KeyError, match="'grape'.*mu"):
        grasp_object("grape", entry)
    with pytest.raises(ValueError, match="fragility"):
        grasp_object("grape", {**DEFAULT_OBJECTS["grape"], "fragility": "glass"})
    targets = {n: grasp_object(n, e).target_N for n, e in DEFAULT_OBJECTS.items()}
    assert targets["grape"] == 0.6 and targets["plum"] == 0.8 and targets["wood_block"] == 1.2


# -- the skin camera: the twin's images through the skin's own image chain -----------------------

GELSIGHT_SKIN = {"body": "gelsight-r10", "pattern": "gelsight-A-II", "look": "gelsight", "noise": 3.0,
                 "source": "render", "light": [[0.95, 0.25, 0.2], [0.25, 0.9, 0.3], [0.2, 0.35, 0.95]]}
SEGMENTATION = {"method": "otsu", "min_area": 3, "box_margin": 3, "gelsight": {"polarity": "dark"}}


def _dimple(n, spacing, depth=0.8, sigma=3.0):
    """A smooth press (h, w, 3) mm: uz a Gaussian dimple, ux/uy pulled towards its centre."""
    from stages.sim.indenters import grid_coords
    gx, gy = grid_coords((n, n), spacing)
    x, y = np.meshgrid(gx, gy)
    uz = -depth * np.exp(-(x ** 2 + y ** 2) / (2 * sigma ** 2))
    return gx, gy, np.stack([0.3 * x * uz, 0.3 * y * uz, uz], -1).astype(np.float32)


def test_skin_camera_renders_and_segments_as_the_skins_frames_are_made():
    """On the sensor's own grid the camera's image of shot i is the markers node's image of a
    render frame i (same Mitsuba render, LEDs, noise seed, segmentation), bit for bit; on the
    twin's 33x33 grid (mesh upsampled back to the 65x65 vertices) it differs on a few edge
    pixels only; its reference is the segmented no-contact render."""
    from stages.control.gripper import SkinCamera
    from stages.control.nodes import skin_camera
    from stages.markers.render import Renderer
    from stages.markers.segment import segment
    from stages.markers.unify import segmentation_params

    markers = gelsight_pattern("A-II")
    gx, gy, disp = _dimple(65, 0.390625)
    flat = np.zeros((65, 65))
    renderer = Renderer(gx, gy, flat, flat == 0, markers, look="gelsight", size=SIZE,
                        light=GELSIGHT_SKIN["light"], noise=3.0, seed=11)
    params = segmentation_params(SEGMENTATION, "gelsight")
    expected = segment(renderer.render(disp, 5)["raw"], **params)
    reference = segment(renderer.render(np.zeros_like(disp), -1)["raw"], **params)
    camera = SkinCamera(gx, gy, markers, spec=GELSIGHT_SKIN, size=SIZE, segmentation=SEGMENTATION,
                        seed=11)
    assert np.array_equal(camera(disp, 5), expected) and np.array_equal(camera.reference, reference)
    assert (expected != reference).sum() > 50                              # the press shows
    assert not np.array_equal(camera(disp, 6), expected)                   # another shot's noise
    node = skin_camera(skin={**GELSIGHT_SKIN, "seed": 11}, markers=markers, sensor=SENSOR,
                       size=SIZE, twin=TWIN, segmentation=SEGMENTATION)
    assert node.grid_shape == (33, 33)
    assert np.array_equal(node.renderer.mesh.x, renderer.mesh.x)           # the same vertices
    assert node.renderer.seed == zlib.crc32(b"control/11/0")               # not a training frame's noise
    assert np.array_equal(node.reference, reference)                       # but the skin's reference
    assert node.reference_seed == 11
    # a re-mounted sensor's fresh take: the reference shot under another noise seed, the shots as before
    fresh = skin_camera(skin={**GELSIGHT_SKIN, "seed": 11}, markers=markers, sensor=SENSOR, size=SIZE,
                        twin=TWIN, segmentation=SEGMENTATION, reference_seed=12)
    renderer.seed = 12
    assert fresh.reference_seed == 12 and fresh.renderer.seed == node.renderer.seed
    assert np.array_equal(fresh.reference, segment(renderer.render(np.zeros_like(disp), -1)["raw"], **params))
    assert 0 < (fresh.reference != node.reference).sum() < 100              # a few marker-edge pixels
    coarse = SkinCamera(node.renderer.mesh.x[1:-1][::2], node.renderer.mesh.y[1:-1][::2], markers,
                        spec=GELSIGHT_SKIN, size=SIZE, segmentation=SEGMENTATION, seed=11, upsample=2)
    assert np.array_equal(coarse.renderer.mesh.x, renderer.mesh.x)
    agree = np.mean(coarse(disp[::2, ::2], 5) == expected)
    assert 0.997 < agree < 1.0
    with pytest.raises(ValueError, match="camera look"):
        SkinCamera(gx, gy, markers, spec={"look": "taxel"}, size=SIZE)


def test_twin_with_a_skin_camera_reads_its_images():
    from stages.control.nodes import skin_camera
    camera = skin_camera(skin=GELSIGHT_SKIN, markers=gelsight_pattern("A-II"), sensor=SENSOR,
                         size=SIZE, twin=TWIN, segmentation=SEGMENTATION, skin_name="gelsight-A-II")
    plum = obj("plum")
    kw = dict(sensor=SENSOR, material=MATERIAL, grid=(33, 33), size=SIZE, camera=camera)
    # the open pad is a shot too: the reference up to camera noise on a few edge pixels
    open_ = GripperTwin(plum, first_shot=40, **kw)
    shot = open_.read_sensors()["left"]
    assert np.array_equal(open_.reference, camera.reference)
    assert np.array_equal(shot, camera(np.zeros((33, 33, 3), np.float32), 41))
    assert 0 < (shot != camera.reference).sum() < 60
    assert open_.markers is camera.markers
    pressed = GripperTwin(plum, width_m=(plum.width_mm - 1.5) * 1e-3, **kw)
    left, right = pressed.read_sensors()["left"], pressed.read_sensors()["right"]
    assert (left != camera.reference).sum() > 10 and not np.array_equal(left, right)
    # each finger's shot: its view of the pad's field, its own camera noise (shots 1, 2)
    from stages.control.gripper import _mirror_x
    field = pressed._solve_frame()[1]
    assert np.array_equal(left, camera(field, 1)) and np.array_equal(right, camera(_mirror_x(field), 2))
    with pytest.raises(ValueError, match=r"camera renders \(96, 96\) images of a \(33, 33\) grid, "
                                         r"the twin has \(64, 64\)"):
        GripperTwin(plum, **{**kw, "size": (64, 64)})


def test_control_node_puts_the_target_skin_on_the_fingers(monkeypatch):
    """control_node: the target skin's sensor, gel, pattern and camera reach the study; the
    supervised model runs the same episodes under control/supervised/... (no passive slip
    runs); skins the flat twin cannot carry are the user's one-line errors."""
    pytest.importorskip("torch")
    import stages.control.nodes as nodes
    from stages.common import InputError
    loaded = []

    def load_predictor(artifact, prefix="genforce_plus"):
        loaded.append((artifact["gain"], prefix))
        return ContactPredictor(artifact["gain"])

    fake = type(sys)("stages.force.model")
    fake.load_predictor = load_predictor
    monkeypatch.setitem(sys.modules, "stages.force.model", fake)
    markers = gelsight_pattern("A-II")
    patterns = {f"markers/gelsight-A-II/{k}": np.asarray(v) for k, v in
                (("centers", markers.centers), ("axes", markers.axes), ("angles", markers.angles),
                 ("pad_size_mm", markers.pad_size_mm))}
    gelsight = {**SENSOR, **GELSIGHT_SKIN}                   # a catalogue entry: mechanics and look
    sensors = {"gelsight-A-II": gelsight,
               "tactip": {**SENSOR, "pattern": "tactip", "look": "tactip", "source": "render"},
               "uskin-3axis": {**SENSOR, "pattern": "uskin", "look": "taxel", "source": "taxels"},
               "dome": {**gelsight, "curvature_radius_mm": 40.0}}
    kw = dict(objects=DEFAULT_OBJECTS, grasp=["grape"], slip=["glue_stick"], size=SIZE,
              duration_s=1.5, pull={**PULL, "monitor_s": 1.0}, seed=0, twin=TWIN,
              sensors=sensors, materials={"r10": MATERIAL}, patterns=patterns,
              segmentation=SEGMENTATION)
    out = nodes.control_node(model={"gain": 3.0}, supervised={"gain": 1.0},
                             model_pair=["gelsight-A-I", "gelsight-A-II"], **kw)
    assert loaded == [(3.0, "genforce_plus"), (1.0, "weights")]
    render_seed = zlib.crc32(b"gelsight-A-II")                 # GELSIGHT_SKIN has no `seed`
    assert out["attrs"]["camera"] == {"skin": "gelsight-A-II", "look": "gelsight",
                                      "reference_seed": render_seed}
    assert out["attrs"]["supervised"] is True
    m = out["metrics"]
    assert "control/slip/glue_stick/slip_mm_passive" in m
    assert "control/supervised/mean/grasp/success" in m and "control/supervised/grasp/grape/pred_error_N" in m
    assert not any(k.startswith("control/supervised/") and "passive" in k for k in m)
    # the model reading a third of the contact grasps otherwise than the one it is measured against
    assert m["control/supervised/grasp/grape/force_error_N"] != pytest.approx(
        m["control/grasp/grape/force_error_N"], abs=1e-3)
    for target, match in (("tactip", "look 'tactip'"), ("uskin-3axis", "look 'taxel'"),
                          ("dome", "'dome' is a dome"), ("unicorn", "'unicorn' is not a sensor")):
        with pytest.raises(InputError, match=match):
            nodes.control_node(model={"gain": 3.0}, model_pair=["gelsight-A-I", target], **kw)
    with pytest.raises(InputError, match="sensor 'gelsight-A-II' has material 'r10', not in materials"):
        nodes.control_node(model={"gain": 3.0}, model_pair=["gelsight-A-I", "gelsight-A-II"],
                           **{**kw, "materials": {}})
    for bad in ("11", 1.5, True, -3):
        with pytest.raises(InputError, match=f"control: reference_seed must be a non-negative integer or null, got {bad!r}"):
            nodes.control_node(model={"gain": 3.0}, model_pair=["gelsight-A-I", "gelsight-A-II"],
                               **{**kw, "reference_seed": bad})
    # the oracle with a supervised model: both run, the oracle's metrics unprefixed
    loaded.clear()
    both = nodes.control_node(model=None, supervised={"gain": 1.0}, model_pair=["gelsight-A-I", "gelsight-A-II"],
                              **{**kw, "slip": []})
    assert loaded == [(1.0, "weights")] and both["attrs"]["predictor"] == "oracle"
    assert both["metrics"]["control/grasp/grape/pred_error_N"] < 1e-6     # the twin's own force
    assert both["metrics"]["control/supervised/grasp/grape/force_error_N"] == pytest.approx(
        m["control/supervised/grasp/grape/force_error_N"])


class TransientPredictor:
    """Reads Fz -0.6 N for the first 4 frames after a reset (a GRU from zero state), then -0.1 N."""

    def reset(self, reference=None):
        self.k = 0

    def step(self, image):
        self.k += 1
        return np.array([0.0, 0.0, -0.6 if self.k <= 4 else -0.1], np.float32)


@pytest.mark.parametrize("warmup_s, at_close", [(0.5, 0.0), (0.0, 0.4)])
def test_the_tare_waits_for_the_models_warm_up(warmup_s, at_close):
    """The baseline averages the tare_s frames after warmup_s: with the default 0.5 s warm-up a
    settled reading (-0.1 N) is tared to 0; without it the first frames' transient enters the
    baseline ((4 x -0.6 - 0.1) / 5 = -0.5 N) and a no-contact frame reads +0.4 N."""
    ep = episode("plum", lambda twin: TransientPredictor(), grasp_s=0.5, twin={"warmup_s": warmup_s})
    close = int(np.searchsorted(ep["time"], ep["marks"]["close"] - 1e-9))
    assert ep["marks"]["close"] == pytest.approx(warmup_s + 0.25)
    assert ep["force_true"][close, 2] == 0.0
    assert ep["force_pred"][close, 2] == pytest.approx(at_close, abs=1e-6)
    np.testing.assert_allclose(ep["baseline_N"], [0.0, 0.0, -0.1 if warmup_s else -0.5], atol=1e-6)
