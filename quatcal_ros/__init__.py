"""
quatcal_ros: hand-eye calibration with the quaternion method of Chou and Kamel (1988).

The subpackages are the rooms of the house; each may import only those below it
(test/test_layers.py checks every module):

    core    the mathematics: quaternions, the paper's solver, least squares, refinement,
            uncertainty, the calibrator (numpy only)
    sim     simulated cells with known answers (numpy)
    stream  from pose streams to samples: pairing, still capture, message checks, the TF
            tree, the time offset, and the Session that the node, the replay and the CSV
            tool all drive
    files   what is read and written on disk: samples CSV, the journal, result files,
            other tools' formats (numpy, yaml)
    vision  camera images: calibration boards, their detection and pose, the fit on the
            pixels (numpy, cv2)
    ros     the ROS side: message conversions, bags, parameters, the nodes (rclpy, rosbags)
    report  the --report page and its figures (matplotlib)
    tools   the command-line tools: solve, replay, plan, demo
"""

import os

# OpenCV's decoders refuse images of more pixels, unless the user set the bound: read once,
# when cv2 loads, so it is set here, before any module of the package imports cv2 (50 MP:
# above any calibration camera; vision/image_decode.py).
MAX_IMAGE_PIXELS = 50_000_000
os.environ.setdefault('OPENCV_IO_MAX_IMAGE_PIXELS', str(MAX_IMAGE_PIXELS))
