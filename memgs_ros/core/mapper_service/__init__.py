"""The mapper's services around the training engine (core/mapping/): the session that owns a live map
(session, its records and tally, keyframe timing), how the node starts it, paces its outputs,
checkpoints, finishes and reports. No ROS: nodes/mapper/ translates messages to these."""
