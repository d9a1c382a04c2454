"""The file formats groomtool reads and writes: one table, the only place that knows their suffixes.

meshio-style: a format has a name and suffixes; ``dispatch.py`` maps the names to the readers and
writers of grooms (``load_groom`` / ``save_groom``, ``READERS`` / ``WRITERS`` by suffix); the rows with
``exports`` are the result formats of ``export.py`` (``groom export --format NAME``; tests/test_io.py
checks that its ``SUFFIXES`` agree); the USD, Alembic and VTK writers check the suffix they are given
against their row.  Plain data, importing nothing: any module of io may use it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Format:
    name: str  #: ``--format`` name and the key of dispatch's reader / writer maps
    suffixes: tuple[str, ...]  #: lower case, with the dot; the first is the default
    reads: bool = False  #: ``load_groom`` reads grooms in it
    writes: bool = False  #: ``save_groom`` writes grooms in it
    exports: bool = False  #: ``groom export --format`` writes results in it
    splittable: bool = False  #: bare vertices without lines: ``strand_length`` applies


# the order of the exporting rows is that of ``--format``'s choices
FORMATS = (
    Format("usd", (".usd", ".usda", ".usdc", ".usdz"), reads=True, exports=True),
    Format("abc", (".abc",), reads=True, exports=True),
    Format("vtp", (".vtp",), exports=True),
    Format("hair", (".hair",), reads=True, writes=True, exports=True),
    Format("obj", (".obj",), reads=True, writes=True, exports=True, splittable=True),
    Format("data", (".data",), reads=True, writes=True),
    Format("ply", (".ply",), reads=True, splittable=True),
)
BY_NAME = {f.name: f for f in FORMATS}


def suffixes(name: str) -> tuple[str, ...]:
    """The suffixes of the format ``name``."""
    return BY_NAME[name].suffixes

