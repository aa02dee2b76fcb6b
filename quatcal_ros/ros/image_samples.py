"""
The calibrator's image input (sensor_input:=image): the board detector and the samples' corners.

`ImageSamples` holds the vision.image_sensor.ImageSensor of board_file, with the still window
of the capture settings, and the corners file beside the samples journal
(files/corners_file.py), so that a resumed session refines on the pixels of its old samples
too. The session's on_sample hook gives each new sample its corners (ImageSensor.keep); the node
calls `keep` with each batch of captured samples to write them (after the journal append),
`sync` with the journal's fsync, `on_pixels` for each new estimate. Write errors are returned
as (level, text) messages to log: the poses, in the samples journal, are what must survive.
"""

from quatcal_ros.files.corners_file import corners_path, CornersFile
from quatcal_ros.vision.board import read_board
from quatcal_ros.vision.image_sensor import ImageSensor


class ImageSamples:
    """The image input of one calibrator node (module docstring)."""

    def __init__(self, config, session_config, samples_path):
        """
        Open the detector of board_file and the corners file beside `samples_path`.

        :param config: the node's settings (board_file, resume).
        :param session_config: its stream.session.SessionConfig (still window, offsets).
        :raises BadInputError: when board_file cannot be read; OSError for the corners file.
        """
        self.sensor = ImageSensor(read_board(config.board_file), session_config=session_config)
        self.file = CornersFile(corners_path(samples_path), config.resume)
        self.messages = list(self.file.messages)
        self.problem = None

    def restore(self, samples):
        """Take back the corners of resumed `samples`; return messages to log."""
        stamps = {sample.stamp_ns for sample in samples}
        rows = [row for row in self.file.restored if row[0] in stamps]
        for stamp_ns, points, pixels in rows:
            self.sensor.restore(stamp_ns, points, pixels)
        if not samples:
            return []
        return [('info', f'corners of {len(rows)} of the {len(samples)} resumed samples read '
                         f'from {self.file.path}')]

    def keep(self, samples):
        """Write the corners the session's samples kept (on_sample); return messages to log."""
        messages = []
        for sample in samples:
            if sample.stamp_ns not in self.sensor.corners:
                messages.append(('warning', f'sample at {sample.stamp_ns * 1e-9:.3f} s: no '
                                            'detected view in its still window, it has no '
                                            'corners (the pose-based estimate uses it)'))
                continue
            points, pixels = self.sensor.corners[sample.stamp_ns]
            messages += self._call(self.file.append, sample.stamp_ns, points, pixels)
        return messages

    def sync(self):
        """Fsync the corners written; return messages to log."""
        return self._call(self.file.sync)

    def on_pixels(self, samples, result, setup, robust):
        """Return the CalibrationResult refined on the corners, or None (too few)."""
        refined = self.sensor.on_pixels(samples, result, setup, robust)
        return None if refined is None else refined[0]

    def restart(self):
        """Forget the corners (~/reset); return what happened to the file, as text."""
        self.sensor.forget()
        try:
            self.file.restart()
        except OSError as error:
            self.problem = f'could not start a new corners file: {error}'
            return f'; {self.problem}'
        return ''

    def camera_changed(self):
        """Start the corners file over on new intrinsics (the old one is moved aside)."""
        try:
            self.file.restart()
        except OSError as error:
            self.problem = f'could not start a new corners file: {error}'
            return [('error', self.problem)]
        return [('warning', f'new intrinsics: {self.file.path} starts over (the corners '
                            'measured with the old ones are moved aside)')]

    def close(self):
        """Fsync and close the corners file."""
        self._call(self.file.close)

    def _call(self, method, *args):
        try:
            method(*args)
        except (OSError, ValueError) as error:
            self.problem = f'{self.file.path}: {error}'
            return [('error', f'{self.problem}: the corners of this sample are kept in memory '
                              'but will not survive a restart')]
        self.problem = None
        return []
