"""ROS messages → canonical track rows: the layer the bag and MCAP adapters share.

The two adapters (``formats/rosbag.py``, ``formats/mcapfile.py``) stay one file per format beside the others
behind the ``FormatAdapter`` registry: they only open their storage and list and decode its messages. What
turns decoded messages into tracks is the same for both, and lives here, one concept per module:

- ``message_types``: which message types are tracks, by kind (pose, object array, tf);
- ``mapping``: which topics are the ego and which are agents (a mapping file, or detected from the types);
- ``messages``: one topic's decoded messages → observations in their own frame;
- ``tf``: the transform tree of a log, looked up vectorised;
- ``world``: observations placed in the world frame and resampled into track rows;
- ``extract``: one log end to end (mapping, extraction, world frame, per-topic problems).

The quaternion maths is core (``logpipe.geometry``): the Argoverse 2 adapter uses it too.
"""
