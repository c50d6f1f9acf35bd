"""Hardware capture into the store, device emulators, and ingest of the authors' dataset.

Modules (imported only when a node runs; this package itself imports nothing):
  poses      sensor-frame millimetres <-> UR TCP poses
  devices    clients: UR5e (ur_rtde), ATI NetF/T (UDP), serial F/T, camera (OpenCV),
             XELA uSkin (WebSocket JSON) and its SLCAN-over-serial option
  twin       the FEM-lite twin a robot drives: contact state, force, marker images, taxels
  emulators  loopback servers backed by the twin: NetF/T, XELA, serial on a pseudo-terminal,
             a camera, the robot's RTDE interfaces; fault injection
  staging    the resumable staging HDF5 file
  session    node `capture`
  authors_layout       where things sit in the authors' released dataset; the sensors it holds
  authors_files        readers of its frames, ft.csv, last.csv, depth and coefficient files
  ingest               node `ingest[sensor]` and `pair_rows`
  authors_calibration  node `authors_calibration[sensor]`: their material-compensation curves
"""


class DeviceError(RuntimeError):
    """A device is missing, misbehaves or disconnects.  The message names the device
    ("netft 127.0.0.1:49152: no reply for 2.0 s after 120 samples"); the CLI reports it as one
    line, exit code 2."""

    user_error = True
