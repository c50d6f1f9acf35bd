"""The whole GenForce data flow in one place: every node, the function it calls, the
artifacts and params keys it reads, and what it fans out over.

Functions are named by import path so that deciding what is stale imports no science.
"""
from pipeline import Graph, Listing, Wiring

GRAPH = Graph()

# which sensors each node runs on, from the sensor catalogue (params `sensors`, `studies`), and
# with `data.source: authors` the authors' released sets under data.root (README, "The authors' dataset")
_CAT = {"sensors": "sensors", "studies": "studies", "data_source": "data.source", "data_root": "data.root"}


def _cat(func: str, **args) -> Listing:
    return Listing(f"stages.catalogue:{func}", _CAT, args)


def _members(study: str, **args) -> Listing:
    return _cat("members", study=study, **args)


# which node holds a sensor's data (the twin's markers or the authors' ingest) and its calibration
# (calibrate or authors_calibration): inputs "{seq[{skin}]}", "{seqs[node]}[{seqs[var]}=@members]"
_SEQ = {"seq": Wiring("stages.catalogue:sequences", _CAT)}
_SEQS = {"seqs": Wiring("stages.catalogue:sequence_node", _CAT)}
_SEQS_GATHER = "{seqs[node]}[{seqs[var]}=@%s]"

# what a render's content depends on: Mitsuba's variant and, for llvm, the pinned JIT target
# (stages.markers.mitsuba_backend), in the cache keys of the nodes that render
_RENDER_TARGET = Listing("stages.markers.mitsuba_backend:render_target", {"backend": "render.backend"})

# -- simulation twin: shapes and where they press ---------------------------------------
GRAPH.node("indenters", "stages.sim.indenters:indenter_set",
           params={"names": "indenters.names", "stl_dir": "indenters.stl_dir", "stl_tip": "indenters.stl_tip"},
           description="the 18 paper indenters + calibration prism, cone and flat punch as watertight meshes")
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
               "max_depth_mm", "n_steps", "repetitions", "indenter", "rate_hz", "shear_mm", "shear_steps")},
           description="3 indentations to d_max and back (a shear leg at d_max), for material compensation")
GRAPH.node("punch_trajectory", "stages.sim.trajectory:calibration_trajectory",
           params={**{k: f"calibration_trajectory.{k}" for k in (
               "max_depth_mm", "n_steps", "repetitions", "rate_hz", "shear_mm", "shear_steps")},
                   "indenter": "plus.punch_indenter"},
           description="the calibration's indentations with a flat punch (genforce_plus's punch_calibration)")

# -- marker representation ----------------------------------------------------------------
GRAPH.node("patterns", "stages.markers.patterns:reference_set",
           params={"names": "patterns.names", "size": "patterns.image_size", "seed": "patterns.twin_seed",
                   # the patterns read from image files (a sensor's pattern, patterns.dir), checksummed
                   "files": Listing("stages.markers.pattern_files:pattern_files",
                                    {"sensors": "sensors", "pattern_dir": "patterns.dir", "names": "patterns.names"})},
           description="reference marker images: 12 sim patterns, GelSight twins, TacTip, uSkin, "
                       "and the patterns of image files")

# -- simulation twin: deformation and force labels ---------------------------------------
GRAPH.node("deform", "stages.sim.deform:deform_sequence",
           inputs={"indenters": "indenters", "sim_trajectory": "sim_trajectory",
                   "collection_trajectory": "collection_trajectory"},
           params={"spec": "sensors.{sensor}", "materials": "materials",
                   "contacts_per_indenter": "deform.collection_contacts_per_indenter",
                   "val_contacts_per_indenter": "deform.validation_contacts_per_indenter",
                   "val_indenters": "splits.val_indenters",
                   "frame_stride": "deform.collection_frame_stride"},
           grid={"sensor": _cat("bodies")},
           description="FEM-lite pad deformation and force labels along a sensor body's trajectory")
GRAPH.node("calibrate", "stages.sim.deform:calibrate",
           inputs={"indenters": "indenters", "trajectory": "calibration_trajectory"},
           params={"spec": "sensors.{sensor}", "materials": "materials"},
           grid={"sensor": _cat("bodies", force_only=True)},
           description="force vs normalised depth, loading and unloading, for material compensation")
GRAPH.node("calibrate_punch", "stages.sim.deform:calibrate",
           inputs={"indenters": "indenters", "trajectory": "punch_trajectory"},
           params={"spec": "sensors.{sensor}", "materials": "materials"},
           grid={"sensor": _cat("bodies", force_only=True)},
           description="force vs normalised depth under a flat punch, for genforce_plus's punch_calibration")
GRAPH.node("contact_check", "stages.sim.checks:contact_check",
           params={"spec": "sensors.sim", "materials": "materials",
                   "radius_mm": "contact_check.radius_mm", "depths_mm": "contact_check.depths_mm"},
           description="the contact solver's force against Hertz on the sim pad's grid")

# -- marker images: render, raw signals, the unified binary marker representation ---------
GRAPH.node("render", "stages.markers.render:render_sequence",
           inputs={"deform": "deform[sensor={spec[body]}]", "patterns": "patterns"},
           params={"spec": "sensors.{skin}", "size": "render.size", "spp": "render.spp",
                   "backend": _RENDER_TARGET},
           grid={"skin": _cat("by_source", source="render")},
           description="Mitsuba render of the deformed skin: raw camera look + ground-truth marker mask")
GRAPH.node("taxels", "stages.markers.uskin:taxel_sequence",
           inputs={"deform": "deform[sensor={spec[body]}]"},
           params={"spec": "sensors.{skin}"},
           grid={"skin": _cat("by_source", source="taxels")},
           description="uSkin 4x4 taxel signals (raw counts near 32768) from the pad's displacement")
GRAPH.node("markers", "stages.markers.unify:marker_sequence",
           inputs={"source": "{spec[source]}[skin={skin}]"},
           params={"spec": "sensors.{skin}", "segmentation": "segmentation"},
           grid={"skin": _cat("active", twin_only=True)},
           description="binary marker images: segmentation of camera looks, signal-to-marker of taxels")

# -- hardware: capture (source nodes: run only when named) ------------------------------------
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
GRAPH.node("capture_calibration", "stages.capture.session:capture_calibration",
           inputs={"trajectory": "calibration_trajectory", "indenters": "indenters"},
           params={"devices": "capture.calibration.devices", "session": "capture.calibration.session",
                   "emulate": "capture.emulate",
                   "rate_hz": "capture.rate_hz", "robot": "capture.robot", "netft": "capture.netft",
                   "serial_ft": "capture.serial_ft", "camera": "capture.camera", "xela": "capture.xela",
                   "slcan": "capture.slcan", "spec": "sensors.{sensor}", "materials": "materials"},
           grid={"sensor": "capture.calibration.sensors"}, source=True,
           description="the calibration indentation pressed into a real sensor, recorded with an F/T sensor")

# -- the authors' released dataset: a sensor per instance, as many as data.root holds ----------
# (the Listings list data.root's folders at plan time; with data.source twin they list none)
_AUTHORS = {"source": "data.source", "root": "data.root"}
GRAPH.node("ingest", "stages.capture.ingest:ingest",
           params={"root": "data.root", "size": "render.size", "modulus_depth_mm": "data.modulus_depth_mm"},
           grid={"sensor": Listing("stages.capture.authors_layout:sensors", _AUTHORS)},
           description="a sensor of the authors' released dataset as a contact sequence")
GRAPH.node("authors_calibration", "stages.capture.authors_calibration:authors_calibration",
           params={"root": "data.root"},
           grid={"sensor": Listing("stages.capture.authors_layout:calibrated_sensors", _AUTHORS)},
           description="a sensor's material-compensation curves as the authors released them")

# -- M2M translation: one generator for every pair, a training-free baseline, image metrics ----
GRAPH.node("m2m_sim", "stages.m2m.fit:pretrain",
           inputs={"markers": "markers[skin=@skins]"},
           params={"skins": _members("sim-m2m"), "train_indenters": "splits.m2m_indenters",
                   "size": "render.size", "steps": "m2m.pretrain.steps",
                   "batch_size": "m2m.pretrain.batch_size", "lr": "m2m.pretrain.lr",
                   "seed": "m2m.pretrain.seed", "width": "m2m.pretrain.width",
                   "timesteps": "m2m.pretrain.timesteps"},
           description="M2M generator trained from scratch on the 12 simulation patterns")
# one fine-tune per set of sensors collected along the same contacts: the twin's, or each of
# the authors' sets (stages.catalogue.m2m_members)
GRAPH.node("m2m", "stages.m2m.fit:finetune",
           inputs={"base": "m2m_sim", "markers": "{seqs[node]}[{seqs[var]}=@members.{fit}]"},
           params={**_SEQS, "members": Wiring("stages.catalogue:m2m_members", _CAT),
                   "train_indenters": "splits.m2m_indenters", "pairs_per_skin": "m2m.finetune.pairs_per_skin", "steps": "m2m.finetune.steps",
                   "batch_size": "m2m.finetune.batch_size", "lr": "m2m.finetune.lr",
                   "seed": "m2m.finetune.seed"},
           grid={"fit": _cat("m2m_fits")},
           description="M2M fine-tuned to the force studies' sensors with location-paired frames of the training indenters")
_EVAL = {"eval_indenters": "splits.test_indenters", "val_indenters": "splits.val_indenters",
         "n_eval": "m2m.n_eval"}
GRAPH.node("translate_sim", "stages.m2m.translate:translate_sim_sequence",
           inputs={"model": "m2m_sim", "source_markers": "markers[skin={source}]",
                   "target_markers": "markers[skin={target}]"},
           params={**_EVAL, "sampler_steps": "m2m.sampler_steps"},
           grid={"source,target": _cat("pairs", study="sim-m2m")},
           description="a simulation pattern's sequence in another pattern's style")
_TRANSFER_PAIRS = _cat("transfer_pairs")
GRAPH.node("translate", "stages.m2m.translate:translate_sequence",
           inputs={"model": "{m2m_of[{source}]}", "source_markers": "{seq[{source}]}", "target_markers": "{seq[{target}]}"},
           params={**_EVAL, **_SEQ, "sampler_steps": "m2m.sampler_steps",
                   "m2m_of": Wiring("stages.catalogue:m2m_of", _CAT),
                   "train_indenters": "splits.train_indenters"},
           grid={"source,target": _TRANSFER_PAIRS},
           description="a calibrated sensor's sequence in an uncalibrated sensor's style")
GRAPH.node("flow_warp", "stages.m2m.translate:flow_warp_sequence",
           inputs={"source_markers": "{seq[{source}]}", "target_markers": "{seq[{target}]}"},
           params={"eval_indenters": "splits.test_indenters", "n_eval": "m2m.n_eval", **_SEQ},
           grid={"source,target": _cat("image_pairs")},
           description="training-free baseline: the source's marker motion warps the target's reference")
GRAPH.node("features", "stages.m2m.translate:image_features",
           inputs={"markers": "{seq[{skin}]}"}, params={**_EVAL, **_SEQ},
           grid={"skin": _cat("active")},
           description="InceptionV3 features of a skin's scored frames (FID/KID)")
# the simulation patterns' features and flow-warps only, so that the study needs no twin
GRAPH.node("sim_m2m", "stages.studies:sim_m2m_study",
           inputs={"features": "features[skin=@skins]", "translated": "translate_sim[*]",
                   "warped": "flow_warp[source=@skins,target=@skins]", "markers": "markers[skin=@skins]"},
           params={"skins": _members("sim-m2m"), "pairs": _cat("pairs", study="sim-m2m"),
                   "kid_subset": "m2m.kid_subset"},
           description="study sim-m2m (paper Fig. 3): FID/KID before / m2m / flow_warp, heatmaps, t-SNE, "
                       "and how well each keeps the deformation (marker motion error)")

# -- force: regressors, transfer with material compensation, the studies ----------------------
_FIT = {"config": "force.config", "steps": "force.steps", "batch_size": "force.batch_size",
        "lr": "force.lr", "finetune_steps": "force.finetune_steps",
        "train_indenters": "splits.train_indenters"}
GRAPH.node("own", "stages.force.fit:fit_own",
           inputs={"markers": "{seq[{skin}]}"},
           params={**{k: v for k, v in _FIT.items() if k != "finetune_steps"}, **_SEQ},
           grid={"skin": _cat("force_sensors"), "seed": "force.seeds"},
           description="force regressor on a skin's own labels: source-only model and oracle")
# a sensor's calibration: the twin's calibrate of its body, the authors' curves, or none (the
# authors' homo set: one gel, no compensation)
GRAPH.node("transfer", "stages.force.fit:fit_transfer",
           inputs={"translated": "translate[source={source},target={target}]",
                   "source_calibration": "{cal[{source}]}", "target_calibration": "{cal[{target}]}",
                   "target_markers": "{seq[{target}]}",
                   "source_punch": "{pcal[{source}]}", "target_punch": "{pcal[{target}]}",
                   "captured_calibrations": "capture_calibration[*]"},
           params={**_FIT, "additions": "plus.additions", **_SEQ,
                   "cal": Wiring("stages.catalogue:calibrations", _CAT),
                   "pcal": Wiring("stages.catalogue:punch_calibrations", _CAT)},
           grid={"source,target": _TRANSFER_PAIRS, "seed": "force.seeds"},
           description="GenForce: regressors on translated images with source labels, raw (genforce), "
                       "compensated (genforce_comp) and with our additions (genforce_plus)")
# each study reads only its own sensors' artifacts (node param `members`, the @ selectors)
_STUDY = {"features": "features[skin=@members]", "markers": _SEQS_GATHER % "members",
          "translated": "translate[source=@members,target=@members]",
          "warped": "flow_warp[source=@members,target=@members]",
          "own": "own[skin=@members]", "transfer": "transfer[source=@members,target=@members]"}
_STUDY_PARAMS = {"test_indenters": "splits.test_indenters", "val_indenters": "splits.val_indenters",
                 "kid_subset": "m2m.kid_subset", "trace_frames": "force.trace_frames"}
for _study, _what in (("homo", "study homo (paper Fig. 4): the five GelSight twins"),
                      ("material", "study material (paper Fig. 5): elastomers of different hardness, "
                                   "with and without compensation"),
                      ("hetero", "study hetero (paper Fig. 6): GelSight, TacTip, uSkin")):
    GRAPH.node(_study, f"stages.studies:{_study}_study", inputs=_STUDY,
               params={**_STUDY_PARAMS, **_SEQS, "members": _members(_study, check=True),
                       "groups": _cat("groups", study=_study)},
               description=_what)

# -- the ablation of genforce_plus: run only when named (`pipeline run ablation`) -------------
GRAPH.node("ablation", "stages.force.study:ablation_study",
           inputs={"transfer": "transfer[*]", "markers": "{seqs[node]}[*]"},
           params={"homo": _cat("groups", study="homo"), "material": _cat("groups", study="material"),
                   "hetero": _cat("groups", study="hetero"),
                   "val_indenters": "splits.val_indenters",
                   "additions": "plus.additions", **_SEQS},
           on_demand=True,
           description="what each addition of genforce_plus earns on the validation indenters, "
                       "beside the seed spread")

# -- the learning curve: run only when named (`pipeline run curves`) ---------------------------
GRAPH.node("curves", "stages.force.curves:curves_study",
           inputs={"own": "own[*]", "transfer": "transfer[*]", "translated": "translate[*]",
                   "markers": "{seqs[node]}[*]"},
           params={"homo": _cat("groups", study="homo"), "material": _cat("groups", study="material"),
                   "hetero": _cat("groups", study="hetero"), "factors": "curves.factors",
                   **{k: v for k, v in _FIT.items()}, "seeds": "force.seeds",
                   "val_indenters": "splits.val_indenters", **_SEQS},
           grid={"study": ["homo", "material", "hetero"]},
           on_demand=True,
           description="the learning curve: a study's oracle and genforce_comp (first seed) on validation "
                       "at 1x and curves.factors times the profile's training length")

# -- control: the transferred force model in a gripper's loop --------------------------------
GRAPH.node("control", "stages.control.nodes:control_node",
           inputs={"model": "transfer[source={model_pair[0]},target={model_pair[1]},seed={seed0[0]}]",
                   "supervised": "own[skin={model_pair[1]},seed={seed0[0]}]", "patterns": "patterns"},
           params={"model_pair": "control.model_pair", "objects": "control.objects",
                   "grasp": "control.grasp", "slip": "control.slip",
                   # the fingers carry the model's target skin: its gel, look and segmentation
                   "sensors": "sensors", "materials": "materials",
                   "segmentation": "segmentation", "backend": _RENDER_TARGET, "size": "render.size",
                   "duration_s": "control.duration_s", "pull": "control.pull", "seed": "control.seed",
                   "reference_seed": "control.reference_seed",
                   "tolerance_N": "control.tolerance_N",
                   # the gripper twin's skins are the twin's: no control run on the authors' data
                   "twin": Wiring("stages.catalogue:twin_data", {"data_source": "data.source"}),
                   # the models of the first regressor seed
                   "seed0": Wiring("stages.catalogue:first_seed", {"seeds": "force.seeds"})},
           description="study control (paper Fig. 7): grasping at a target force, slip avoidance")

# -- the answer first: the studies' test figures beside the paper's ------------------------
GRAPH.node("summary", "stages.summary:summary",
           inputs={"homo": "homo", "material": "material", "hetero": "hetero", "sim_m2m": "sim_m2m"},
           description="the studies' results on the test split beside the paper's figures, and the "
                       "paper's targets (the report's first tables; docs/results.md)")
