"""
From pose streams to samples.

The time-indexed pose buffer, pairing, still capture, message checks, the TF tree, the time
offset and the Session (no ROS, no file formats).
"""
