"""Sustained capture rate against the loopback emulators, and per-device read latency.

Run: python benchmarks/capture.py [--quick]   (about 30 s on a 2-core CPU; --quick: two device
sets and 20 latency samples)

The capture node runs emulated (the FEM-lite twin solves every robot pose) on the GelSight
twin's ci-size solver grid (33 x 33), unpaced (rate_hz 0), along the collection protocol for
one indenter and point (0.5 mm depth steps to 1 mm, 4 shear directions, every 3rd sample of
each movement).  Each device set prints frames/s of captured contact time and its ratio to the
40 Hz the paper recorded at (> 1: the capture side keeps up; a real UR5e's moveL between
samples is the bottleneck on hardware).  Camera frames are stored at 640 x 480.  Then every
device is read 60 times after as many robot moves; latency = the read call's wall time.
"""
import argparse
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np                                                        # noqa: E402
import yaml                                                               # noqa: E402

from benchmarks.summary import drain, record                              # noqa: E402
from stages.capture.devices import Robot                                  # noqa: E402
from stages.capture.emulators import Emulators                            # noqa: E402
from stages.capture.poses import to_pose                                  # noqa: E402
from stages.capture.session import capture                                # noqa: E402
from stages.sim.indenters import indenter_set                             # noqa: E402
from stages.sim.trajectory import collection_trajectory                   # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER_HZ = 40.0


def params():
    p = yaml.safe_load(open(os.path.join(ROOT, "params.yaml")))
    ci = yaml.safe_load(open(os.path.join(ROOT, "params", "ci.yaml")))
    p["sensors"]["gelsight-r10"].update(ci["sensors"]["gelsight-r10"])
    return p


def run(traj, meshes, p, devices, rate_hz=0.0, **device_params):
    base = {k: {} for k in ("robot", "netft", "serial_ft", "camera", "xela", "slcan")}
    base.update(device_params)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        final = drain(capture(trajectory=traj, devices=devices, sensor="gelsight-r10", rate_hz=rate_hz,
                              staging_dir=tmp, emulate=True, session={"frame_stride": 3}, indenters=meshes,
                              spec=p["sensors"]["gelsight-r10"], materials=p["materials"], **base))
        return final["attrs"], time.perf_counter() - t


def latency(traj, meshes, p, samples=60):
    devices = ["robot", "netft", "serial_ft", "camera", "xela", "slcan"]
    spec = p["sensors"]["gelsight-r10"]
    from stages.sim.indenters import mesh_from_artifact
    emu = Emulators(devices, {}, spec=spec, material=p["materials"]["r10"],
                    mesh_of=lambda n: mesh_from_artifact(meshes, n))
    times = {d: [] for d in devices}
    with emu:
        emu.world.mount("sphere")
        for c in emu.clients.values():
            c.open()
        robot = emu.clients["robot"]
        origin = Robot.defaults["origin"]
        rows = np.flatnonzero(traj["contact_id"] == 0)[:samples]
        for r in rows:
            pos = traj["position"][r]
            t = time.perf_counter()
            robot.move(to_pose(pos, origin))
            times["robot"].append(time.perf_counter() - t)
            since = time.time()
            for d in devices[1:]:
                t = time.perf_counter()
                emu.clients[d].read(since)
                times[d].append(time.perf_counter() - t)
        for c in emu.clients.values():
            c.close()
    return times


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two device sets, 20 latency samples")
    args = ap.parse_args()
    samples = 20 if args.quick else 60
    p = params()
    art = indenter_set(["sphere"])
    meshes = {f"meshes/sphere/{k}": v for k, v in art["meshes"]["sphere"].items()}
    traj = collection_trajectory(indenters=["sphere"], n_points=1, depth_step_mm=0.5, max_depth_mm=1.0,
                                 n_directions=4)
    warm = collection_trajectory(indenters=["sphere"], n_points=1, depth_step_mm=1.0, max_depth_mm=1.0,
                                 n_directions=1, speed_mm_s=40.0)
    run(warm, meshes, p, ["robot", "netft", "camera"])            # solver kernel tables, imports
    print(f"sustained capture rate (emulated, unpaced), vs the paper's {PAPER_HZ:g} Hz")
    print(f"{'devices':34s} {'frames':>6s} {'wall s':>7s} {'frames/s':>9s} {'ratio':>6s}")
    sets = [["robot", "netft"], ["robot", "netft", "camera"], ["robot", "serial_ft", "xela"],
            ["robot", "netft", "slcan", "camera"]]
    for devices in (sets[::3] if args.quick else sets):
        attrs, wall = run(traj, meshes, p, devices)
        rate = attrs["rate_hz_achieved"]
        print(f"{' + '.join(devices):34s} {attrs['frames']:6d} {wall:7.2f} {rate:9.1f} {rate / PAPER_HZ:6.2f}")
        record("capture", f"capture rate vs 40 Hz, {' + '.join(devices)}", f"{rate:.1f} frames/s",
               rate / PAPER_HZ, ">= 1")
    attrs, wall = run(traj, meshes, p, ["robot", "netft", "camera"], rate_hz=PAPER_HZ)
    print(f"{'robot + netft + camera, paced 40':34s} {attrs['frames']:6d} {wall:7.2f} "
          f"{attrs['rate_hz_achieved']:9.1f} {attrs['rate_hz_achieved'] / PAPER_HZ:6.2f}")
    record("capture", "paced capture at 40 Hz, robot + netft + camera",
           f"{attrs['rate_hz_achieved']:.1f} frames/s", attrs["rate_hz_achieved"] / PAPER_HZ)
    print(f"\nper-device latency over {samples} samples (robot: moveL incl. the twin's contact solve)")
    print(f"{'device':10s} {'mean ms':>8s} {'p95 ms':>8s}")
    for d, ts in latency(traj, meshes, p, samples).items():
        ts = 1e3 * np.asarray(ts)
        print(f"{d:10s} {ts.mean():8.2f} {np.percentile(ts, 95):8.2f}")


if __name__ == "__main__":
    main()
