"""
An image dataset folder (DESIGN.md contract 5) as samples, views and the reasons for refusals.

    DIR/images/<name>.png|.jpg   DIR/robot_poses.csv   DIR/camera_info.yaml   DIR/board.yaml

`load_image_dataset` detects the board in each image listed in robot_poses.csv (detect.py);
each view that passes its checks becomes a still sample: the link pose of its row and the
board pose T_camera_board with the PnP covariance (which weighs it in the pose-based
refinement). The refused views are listed with their named reasons; nothing is dropped
silently. Errors in the files name the file, the row and the field.
"""

from collections import Counter
from dataclasses import dataclass, field
import os
from pathlib import Path
import stat
import unicodedata

from quatcal_ros.core.pose import Sample
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.files.samples_csv import check_header, parse_numbers, pose_from_values
from quatcal_ros.files.text_input import BadInputError, csv_rows, read_text
from quatcal_ros.vision.board import read_board
from quatcal_ros.vision.camera import read_camera_yaml
from quatcal_ros.vision.detect import detect
from quatcal_ros.vision.image_decode import decode_gray
from quatcal_ros.vision.view import Checks

# The folder's layout (DESIGN.md contract 5): these files, and the images in IMAGES_FOLDER.
LAYOUT_FILES = ('robot_poses.csv', 'camera_info.yaml', 'board.yaml')
IMAGES_FOLDER = 'images'
# An image file larger than this is not a camera frame (a 100-megapixel 16-bit TIFF is 200 MB).
MAX_IMAGE_BYTES = 256 * 1024 * 1024
POSE_COLUMNS = ('image', 'link_x', 'link_y', 'link_z', 'link_qx', 'link_qy', 'link_qz',
                'link_qw')


@dataclass
class ImageDataset:
    """The views of a folder: the samples of those used, and why the others were refused."""

    board: object
    camera: object
    names: list = field(default_factory=list)      # images used, in file order
    samples: list = field(default_factory=list)    # one per image used
    views: list = field(default_factory=list)      # detect.View of each image used
    refused: list = field(default_factory=list)    # {'image', 'reason', 'detail'}
    unlisted: list = field(default_factory=list)   # images in the folder that no row names

    def refused_json(self):
        return list(self.refused)

    def refusal_summary(self):
        """Return the refusals in words: each reason, its count, its first image and detail."""
        first, counts = {}, Counter(entry['reason'] for entry in self.refused)
        for entry in self.refused:
            first.setdefault(entry['reason'], entry)
        return '; '.join(f"{reason} {count} (first: {first[reason]['image']}: "
                         f"{first[reason]['detail']})" for reason, count in counts.most_common())

    def unlisted_summary(self):
        """Say which images no row names (`unlisted`): they have no robot pose."""
        return (f'{len(self.unlisted)} image(s) in {IMAGES_FOLDER}/ are not used: no row of '
                f'robot_poses.csv names them ({_first_names(self.unlisted)}), so they have no '
                'robot pose; is a row missing?')

    def refuse_copies(self, copies):
        """Refuse the views {position used: position of the used view it repeats}."""
        self.refused += [{'image': self.names[copy], 'reason': 'repeated_view',
                          'detail': f'the same robot pose and board pose as '
                                    f'{self.names[original]}: a copy'}
                         for copy, original in sorted(copies.items())]
        for copy in sorted(copies, reverse=True):
            del self.names[copy], self.samples[copy], self.views[copy]

    def corners(self):
        """Return [(object_points, image_points)] of each view used, as the samples."""
        return [(view.object_points, view.image_points) for view in self.views]


def check_layout(folder):
    """Raise BadInputError naming the first entry of the layout that `folder` lacks."""
    folder = Path(folder)
    layout = (f'an image dataset folder holds {IMAGES_FOLDER}/, {", ".join(LAYOUT_FILES[:-1])} '
              f'and {LAYOUT_FILES[-1]}')
    for name in LAYOUT_FILES + (IMAGES_FOLDER,):
        path, want_folder = folder / name, name == IMAGES_FOLDER
        try:
            if not path.exists():
                problem = 'missing'
            elif not (path.is_dir() if want_folder else path.is_file()):
                problem = 'not a directory' if want_folder else 'not a file'
            else:
                problem = None
                if want_folder:
                    next(path.iterdir(), None)      # can the images be listed?
        except OSError as error:
            raise BadInputError(f'{path}: cannot read: {error.strerror}') from None
        if problem is not None:
            raise BadInputError(f'{folder}: {name} {problem} ({layout})')


def load_image_dataset(folder, checks=Checks(), progress=None):
    """Read and detect the folder (module docstring); progress(done, total) after each image."""
    folder = Path(folder)
    check_layout(folder)
    poses_file, camera_file, board_file = LAYOUT_FILES
    rows = read_robot_poses(folder / poses_file)
    board = read_board(folder / board_file)
    camera = read_camera_yaml(folder / camera_file)
    dataset = ImageDataset(board, camera)
    for index, (image_name, link) in enumerate(rows):
        gray, problem = _read_gray(folder / IMAGES_FOLDER / image_name)
        if gray is None:
            dataset.refused.append({'image': image_name, 'reason': 'unreadable_image',
                                    'detail': problem})
        else:
            view = detect(gray, board, camera, checks)
            if view.ok:
                dataset.names.append(image_name)
                dataset.views.append(view)
                dataset.samples.append(Sample(index * NS_PER_S, link, view.pose))
            else:
                dataset.refused.append({'image': image_name, 'reason': view.refused,
                                        'detail': view.detail})
        if progress is not None:
            progress(index + 1, len(rows))
    unlisted = _unlisted(folder / IMAGES_FOLDER, {name for name, _ in rows})
    if not _name_unlisted(dataset, unlisted):   # (else a missing image's refusal names them)
        dataset.unlisted = [name for name in unlisted
                            if Path(name).suffix.lower() in IMAGE_SUFFIXES]
    return dataset


# Files a desktop leaves in a folder of pictures: no image a row could have meant.
SYSTEM_FILES = ('thumbs.db', 'desktop.ini')
# What an image's file name ends with (ImageDataset.unlisted).
IMAGE_SUFFIXES = ('.png', '.jpg', '.jpeg', '.bmp', '.tif', '.tiff', '.pgm', '.ppm')


def _unlisted(images, listed):
    """Return the files in the folder `images` that no row names (not hidden, not a desktop's)."""
    try:
        return sorted(p.name for p in images.iterdir() if p.name not in listed
                      and p.is_file() and not p.name.startswith('.')
                      and p.name.lower() not in SYSTEM_FILES)
    except OSError:
        return []


def _name_unlisted(dataset, unlisted):
    """Add to each missing image's refusal the files no row names (renamed?); say if any."""
    missing = [entry for entry in dataset.refused if entry['detail'].startswith('missing')]
    if not (missing and unlisted):
        return False
    for entry in missing:
        entry['detail'] += (f'; {IMAGES_FOLDER}/ holds {len(unlisted)} file(s) that no row of '
                            f'robot_poses.csv names ({_first_names(unlisted)}): are the rows '
                            'named after them?')
    return True


def _first_names(names):
    """Return the first three of `names`, ', ...' after them when there are more."""
    return ', '.join(names[:3]) + (', ...' if len(names) > 3 else '')


def _read_gray(path):
    """Return (the image at `path` in gray, None) or (None, why it cannot be read)."""
    try:
        status = os.stat(path)   # before opening: a FIFO would block the open
        if not stat.S_ISREG(status.st_mode):
            return None, 'not a regular file'
        if status.st_size > MAX_IMAGE_BYTES:
            return None, f'larger than {MAX_IMAGE_BYTES // (1024 * 1024)} MiB'
        with open(path, 'rb') as stream:
            data = stream.read(MAX_IMAGE_BYTES + 1)
    except FileNotFoundError:
        wanted = Path(path)
        others = sorted(p.name for p in wanted.parent.iterdir() if p.stem == wanted.stem)
        return None, 'missing' + (f' ({", ".join(others)} exists)' if others else '')
    except OSError as error:
        return None, f'cannot read: {error.strerror}'
    return decode_gray(data)


def read_robot_poses(path):
    """Return [(image name, T_base_link Pose)] of robot_poses.csv; BadInputError names the row."""
    name = str(path)
    records = csv_rows(read_text(path), name)
    header = [column.strip() for column in next(records, (1, []))[1]]
    check_header(header, POSE_COLUMNS, f'{name}, row 1 (header)')
    index = {c: header.index(c) for c in POSE_COLUMNS}
    rows, seen = [], {}
    for line, row in records:
        if not row or all(not cell.strip() for cell in row):
            continue
        image = row[index['image']].strip() if index['image'] < len(row) else ''
        control = any(unicodedata.category(c) == 'Cc' for c in image)   # (NUL: os.stat)
        if not image or '/' in image or image in seen or control:
            why = ('empty' if not image else
                   f'already on row {seen[image]}' if image in seen else
                   'not a file name: it holds a control character' if control else
                   f'a file name in {IMAGES_FOLDER}/, without the folder: '
                   f'{image.rsplit("/", 1)[1]!r}' if image.startswith(IMAGES_FOLDER + '/') else
                   f'a file name in {IMAGES_FOLDER}/ (no folders)')
            raise BadInputError(f'{name}, row {line}, field image: {image!r}: {why}')
        seen[image] = line
        values = parse_numbers(row, {c: index[c] for c in POSE_COLUMNS[1:]}, name, line)
        rows.append((image, pose_from_values(values, 'link', name, line)))
    if not rows:
        raise BadInputError(f'{name}: no rows')
    return rows
