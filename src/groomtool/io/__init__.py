"""Groom and head input/output: readers and writers per format, validation, atomic writes.

Every reader returns a validated ``Groom`` in metres; every writer replaces its target atomically.
"""

from .atomic import atomic_open, atomic_path, atomic_write
from .dispatch import READERS, WRITERS, load_groom, save_groom
from .hair import read_hair, write_hair
from .head import load_head
from .obj import read_obj, write_obj
from .ply import read_ply
from .usc import read_data, write_data
from .validate import validate

__all__ = [
    "READERS", "WRITERS", "atomic_open", "atomic_path", "atomic_write", "load_groom", "load_head",
    "read_data", "read_hair", "read_obj", "read_ply", "save_groom", "validate", "write_data",
    "write_hair", "write_obj",
]
