"""
What is read and written on disk.

Samples CSV, the journal, result files and other tools' formats (numpy and yaml).
"""
