"""Shared inputs of the capture tests: the ci sensor catalogue, two indenter meshes, a tiny
collection trajectory (2 contacts x 24 frames), and a runner that drains the capture node."""
import pytest

from tests.helpers import concat, drain, load_params


@pytest.fixture(scope="session")
def ci():
    return load_params("ci")


@pytest.fixture(scope="session")
def meshes():
    from stages.sim.indenters import indenter_set
    art = indenter_set(["sphere", "prism"])
    return {f"meshes/{n}/{k}": v for n, m in art["meshes"].items() for k, v in m.items()}


@pytest.fixture(scope="session")
def trajectory():
    from stages.sim.trajectory import collection_trajectory
    return collection_trajectory(indenters=["sphere", "prism"], n_points=1, n_directions=2,
                                 depth_step_mm=0.5, max_depth_mm=0.5, speed_mm_s=20.0)


@pytest.fixture(scope="session")
def run_capture(ci, meshes, trajectory):
    """run_capture(staging_dir, devices=..., sensor=..., **device params) -> (arrays, final)."""
    from stages.capture.session import capture

    def run(staging_dir, devices=("robot", "netft", "camera"), sensor="gelsight-r10", session=None, **params):
        base = {"robot": {}, "netft": {"retry_s": 0.02, "timeout_s": 0.5,
                                       "emulator": {"bias": [0.12, -0.08, 0.35, 0.004, -0.002, 0.001]}},
                "serial_ft": {"retry_s": 0.02, "timeout_s": 0.5}, "camera": {"out_size": [60, 80]},
                "xela": {"timeout_s": 0.5}, "slcan": {"retry_s": 0.02, "timeout_s": 0.5}}
        for k, v in params.items():
            base[k] = {**base[k], **v}
        chunks, final = drain(capture(trajectory=trajectory, devices=list(devices), sensor=sensor, rate_hz=0.0,
                                      staging_dir=str(staging_dir), emulate=True, session=session,
                                      indenters=meshes, spec=ci["sensors"][sensor], materials=ci["materials"],
                                      **base))
        return concat(chunks), final
    return run
