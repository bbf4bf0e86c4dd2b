"""File-system plumbing of every read and write (private).

Atomic publication, disk-space checks, early write-back, writer threads and read guards.
"""
