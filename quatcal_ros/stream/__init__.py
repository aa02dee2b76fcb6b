"""
From pose streams to samples.

Pairing, still capture, message checks, the TF tree, the time offset and the Session (no ROS,
no file formats).
"""
