"""agos.deploy.ros2: a run on a ROS 2 graph over rmw_zenoh (``agos ros2 bridge``; docs/DEPLOY.md, "ROS 2 (rmw_zenoh)").

``graph``: one ROS 2 node on a zenoh session, in rmw_zenoh's key layout (data keys, liveliness
tokens, attachments) with CDR from ``rosbags``; ``topics``: agos messages as ROS 2 messages and the
topic each goes on; ``bridge``: the process, which republishes a run and answers a role's decisions
with what a ROS 2 node publishes. Imports runtime and agents (the agent service) only; needs the
``robotics`` extra (rosbags).
"""
