"""Samples journals on disk, as the journal and resume tests make and inspect them."""

from pathlib import Path

from quatcal_ros.files import journal
from quatcal_ros.files.journal import JournalHeader

HEADER = JournalHeader('eye_in_hand', 'tool0', 'camera')


def write_journal(path, samples, header=HEADER, now=None):
    """Write a fresh journal of `samples` at `path`; return its bytes."""
    opened, _ = journal.start(path, header, resume=False, now=now)
    for sample in samples:
        opened.append(sample)
    opened.close()
    return path.read_bytes()


def aside_files(directory, tag):
    """Return the files moved aside in `directory` with `tag` ('corrupt', 'old', ...)."""
    return sorted(p for p in Path(directory).iterdir() if f'.{tag}-' in p.name)
