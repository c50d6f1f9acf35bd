"""Force control in a gripper twin: the paper's grasp-at-target-force and slip avoidance tasks.

gripper.py the Gripper interface and GripperTwin; objects.py the object catalogue;
controller.py GraspController, SlipAvoider, OraclePredictor; episodes.py one grasp or slip
episode and its metrics; nodes.py the `control` study node.
"""
