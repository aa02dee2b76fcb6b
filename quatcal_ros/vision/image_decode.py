"""
Encoded images (files, CompressedImage messages) to the 8-bit gray the detector takes.

One decoder for both, which keeps the pixels as the camera stored them:

- An EXIF Orientation tag is ignored: the intrinsics describe the sensor's pixels (OpenCV turned
  a JPEG tagged "rotate 180" before detection, and the mounting came out turned 180 degrees
  with a passing validation).
- 16-bit data (a 16-bit PNG, mono16) is shifted down to its own top 8 bits: a 12-bit camera's
  values (0 to 4095) lost all but 4 bits when cut to the high byte, and no board was found.
- At most MAX_IMAGE_PIXELS: OpenCV refuses a larger image before decoding it (the package sets
  OPENCV_IO_MAX_IMAGE_PIXELS before cv2 loads, quatcal_ros/__init__.py; a 1 MB PNG of
  30000 x 30000 pixels decoded to 900 MB).
"""

import os

import cv2
import numpy as np

FLAGS = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_IGNORE_ORIENTATION


def decode_gray(data):
    """Return (8-bit gray image, None) of encoded bytes, or (None, why they do not decode)."""
    buffer = np.frombuffer(data, np.uint8)
    try:
        image = cv2.imdecode(buffer, FLAGS) if buffer.size else None
    except cv2.error as error:
        if 'CV_IO_MAX_IMAGE_PIXELS' in str(error):
            limit = os.environ.get('OPENCV_IO_MAX_IMAGE_PIXELS', '')
            return None, f'more pixels than OPENCV_IO_MAX_IMAGE_PIXELS ({limit})'
        return None, f'not an image OpenCV can read ({str(error).strip().splitlines()[-1]})'
    if image is None:
        return None, 'not an image OpenCV can read'
    if image.dtype not in (np.uint8, np.uint16):   # a float TIFF or HDR file
        return None, f'{image.dtype} pixels: an 8- or 16-bit image is expected'
    return gray_8bit(image), None


def gray_8bit(image):
    """Return a uint8 or uint16 gray image as uint8: 16 bits shifted to their top 8 in use."""
    if image.dtype == np.uint8:
        return image
    shift = max(int(image.max()).bit_length() - 8, 0)
    return (image >> shift).astype(np.uint8)
