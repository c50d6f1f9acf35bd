"""The whole GenForce data flow in one place: every node, the function it calls, the
artifacts and params keys it reads, and what it fans out over.

Functions are named by import path so that deciding what is stale imports no science.
"""
from pipeline import Graph

GRAPH = Graph()

# -- simulation twin: shapes and where they press ---------------------------------------
GRAPH.node("indenters", "stages.sim.indenters:indenter_set",
           params={"names": "indenters.names"},
           description="the 18 paper indenters + calibration prism/cone as watertight meshes")
GRAPH.node("sim_trajectory", "stages.sim.trajectory:sim_grid_trajectory",
           params={"positions_mm": "sim_trajectory.positions_mm", "depths_mm": "sim_trajectory.depths_mm",
                   "indenters": "sim_trajectory.indenters"},
           description="the paper's simulation grid: positions x depths per indenter")
GRAPH.node("collection_trajectory", "stages.sim.trajectory:collection_trajectory",
           params={k: f"collection_trajectory.{k}" for k in (
               "n_points", "point_offset_mm", "depth_step_mm", "max_depth_mm", "shear_radius_mm",
               "n_directions", "rate_hz", "speed_mm_s", "indenters")},
           description="the real-collection protocol: 5 points, depth steps, 8 shear directions")
GRAPH.node("calibration_trajectory", "stages.sim.trajectory:calibration_trajectory",
           params={k: f"calibration_trajectory.{k}" for k in (
               "max_depth_mm", "n_steps", "repetitions", "indenter", "rate_hz")},
           description="3 indentations to d_max and back, for material compensation")

# -- marker representation ----------------------------------------------------------------
GRAPH.node("patterns", "stages.markers.patterns:reference_set",
           params={"names": "patterns.names", "size": "patterns.image_size", "seed": "patterns.twin_seed"},
           description="reference marker images: 12 sim patterns, GelSight twins, TacTip, uSkin")

# -- simulation twin: deformation and force labels ---------------------------------------
GRAPH.node("deform", "stages.sim.deform:deform_sequence",
           inputs={"indenters": "indenters", "sim_trajectory": "sim_trajectory",
                   "collection_trajectory": "collection_trajectory"},
           params={"spec": "sensors.{sensor}", "materials": "materials",
                   "contacts_per_indenter": "deform.collection_contacts_per_indenter",
                   "frame_stride": "deform.collection_frame_stride"},
           grid={"sensor": "deform.sensors"},
           description="FEM-lite pad deformation and force labels along the sensor's trajectory")
GRAPH.node("calibrate", "stages.sim.deform:calibrate",
           inputs={"indenters": "indenters", "trajectory": "calibration_trajectory"},
           params={"spec": "sensors.{sensor}", "materials": "materials"},
           grid={"sensor": "calibrate.sensors"},
           description="force vs normalised depth, loading and unloading, for material compensation")
GRAPH.node("contact_check", "stages.sim.checks:contact_check",
           params={"spec": "sensors.sim", "materials": "materials",
                   "radius_mm": "contact_check.radius_mm", "depths_mm": "contact_check.depths_mm"},
           description="the contact solver's force against Hertz on the sim pad's grid")

# -- marker images: render, raw signals, the unified binary marker representation ---------
GRAPH.node("render", "stages.markers.render:render_sequence",
           inputs={"deform": "deform[sensor={spec[sensor]}]", "patterns": "patterns"},
           params={"spec": "skins.{skin}", "size": "render.size", "spp": "render.spp",
                   "backend": "render.backend"},
           grid={"skin": "render.skins"},
           description="Mitsuba render of the deformed skin: raw camera look + ground-truth marker mask")
GRAPH.node("taxels", "stages.markers.uskin:taxel_sequence",
           inputs={"deform": "deform[sensor={spec[sensor]}]"},
           params={"spec": "skins.{skin}"},
           grid={"skin": "taxels.skins"},
           description="uSkin 4x4 taxel signals (raw counts near 32768) from the pad's displacement")
GRAPH.node("markers", "stages.markers.unify:marker_sequence",
           inputs={"source": "{spec[source]}[skin={skin}]"},
           params={"spec": "skins.{skin}", "segmentation": "segmentation"},
           grid={"skin": "render.skins + taxels.skins"},
           description="binary marker images: segmentation of camera looks, signal-to-marker of taxels")

# -- hardware: capture and ingest (source nodes: run only when named) ----------------------
GRAPH.node("capture", "stages.capture.session:capture",
           inputs={"trajectory": "collection_trajectory", "indenters": "indenters"},
           params={"devices": "capture.devices", "emulate": "capture.emulate", "sensor": "capture.sensor",
                   "rate_hz": "capture.rate_hz", "session": "capture.session", "robot": "capture.robot",
                   "netft": "capture.netft", "serial_ft": "capture.serial_ft", "camera": "capture.camera",
                   "xela": "capture.xela", "slcan": "capture.slcan",
                   # the emulators' twin (used only with capture.emulate)
                   "spec": "sensors.gelsight-r10", "materials": "materials"},
           source=True,
           description="a UR5e presses the trajectory into the sensor; F/T, camera, uSkin recorded")
GRAPH.node("ingest", "stages.capture.ingest:ingest",
           params={"root": "ingest.root", "sensor": "ingest.sensor", "size": "ingest.size"}, source=True,
           description="the paper authors' published dataset layout as a contact sequence")
