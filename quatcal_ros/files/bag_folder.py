"""
What a rosbag2 recording is on disk: a folder with its index and its storage files.

One description for the replay (the files it reads, a split recording given by one of its
files, a folder that lost its index) and for the output-path check (the files no output may
replace). No rosbags here: the path check of `solve` must not import it.
"""

from pathlib import Path

INDEX = 'metadata.yaml'
READABLE_SUFFIXES = ('.db3', '.mcap')                  # sqlite3 and mcap storage files
STORAGE_SUFFIXES = READABLE_SUFFIXES + ('.zstd',)      # and compressed ones


def storage_files(folder, suffixes=STORAGE_SUFFIXES):
    """Return the files in `folder` with these suffixes (sorted); none when it cannot be listed."""
    try:
        return sorted(entry for entry in Path(folder).iterdir() if entry.suffix in suffixes)
    except OSError:
        return []
