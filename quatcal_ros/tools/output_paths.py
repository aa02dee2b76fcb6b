"""
Output paths that would destroy an input or cannot be written: refused before a tool reads.

`solve victim.csv --report victim.csv` once replaced the samples with a report page, and
`replay BAG --samples-out BAG/bag_0.db3` the recording with a CSV. `output_problem` names such
an output: one that is an input file, one of the files an image dataset folder is made of (its
layout and images/), anything in a bag's folder (or, for a bag given as its storage file, that
folder's index and storage files), or another output's path. A new file beside the inputs, or
in a dataset folder, is fine (a report beside the images). It also names an output that
could not be written at all (a device, a directory, a parent that is a file, a symbolic link
loop on the way, a folder without write permission), so that no output is written before
another one fails.
"""

import os
from pathlib import Path

from quatcal_ros.files import bag_folder


def real(path):
    """Return the absolute path with ~ and symbolic links resolved; never raises."""
    return Path(os.path.realpath(os.path.expanduser(os.fspath(path))))


def protected(kind, path):
    """
    Return (files, folders) that the input `path` is made of (folders: everything below).

    kind: 'file'; 'dataset' (an image dataset folder: its layout files and images/); 'bag'
    (a rosbag2 folder, all of it, or one storage file: it and its folder's index and storage
    files).
    """
    path = real(path)
    if kind == 'dataset':
        from quatcal_ros.vision.dataset import IMAGES_FOLDER, LAYOUT_FILES   # cv2: images only
        return {path / name for name in LAYOUT_FILES}, {path / IMAGES_FOLDER}
    if kind == 'bag' and path.is_dir():
        return set(), {path}
    if kind == 'bag':
        return ({path, path.parent / bag_folder.INDEX}
                | set(bag_folder.storage_files(path.parent)), set())
    return {path}, set()


def output_problem(inputs, outputs):
    """
    Say why the outputs would destroy an input or each other or cannot be written, or None.

    inputs: [(kind, path)] of the paths read (protected's kinds; a path None is skipped);
    outputs: {option: path or None}.
    """
    files, folders = set(), set()
    for kind, source in inputs:
        if source:
            more_files, more_folders = protected(kind, source)
            files |= more_files
            folders |= more_folders
    seen = {}
    for option, path in outputs.items():
        if not path:
            continue
        target = real(path)
        if target in files or target in folders or folders & set(target.parents):
            return (f'{option} {path}: that is an input file (or in an input folder): choose '
                    'another path, nothing was written')
        if target in seen:
            return (f'{seen[target]} and {option} name the same file {path}: one would '
                    'replace the other')
        seen[target] = option
        unwritable = _unwritable(target)
        if unwritable:
            return f'{option} {path}: {unwritable}: choose another path, nothing was written'
    return None


def _unwritable(target):
    """Return why no file can be written at the resolved path `target`, or None."""
    try:
        # real() resolved every link that leads anywhere: one left on the way is a loop
        loop = next((p for p in (target, *target.parents) if p.is_symlink()), None)
        if loop is not None:
            return f'{loop} is a symbolic link that leads back to itself'
        if target.exists() and not target.is_file():
            return 'exists and is not a regular file'
        folder = next(p for p in target.parents if p.exists())   # the root exists
    except OSError as error:   # a folder on the way that may not be searched
        return f'cannot look there: {error.strerror}'
    if not folder.is_dir():
        return f'{folder} is a file, not a folder'
    if not os.access(folder, os.W_OK | os.X_OK):
        return f'no permission to write in {folder}'
    return None
