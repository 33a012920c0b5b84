"""Stitch patterns as charts: which stitch of each course is knit or purl.

A chart is a grid of courses × stitches, course 0 the bottom (the first
knitted, cast-on loops not counted), stitch 0 the left one, each read from
the technical face (the side where a knit's legs show as V's): a knit
stitch ``K`` is a loop pulled through its parent towards the face, a purl
``P`` the same loop pulled through from the other side.

Patterns come by name, sized by rows × cols, each starting at the bottom
left (course i, stitch j):

=========  =========================  ==================
jersey     K everywhere               purl(i, j) = 0
rib1x1     ``KPKP…`` every course     purl(i, j) = j mod 2
rib2x2     ``KKPP…`` every course     purl(i, j) = ⌊j/2⌋ mod 2
garter     a course of K, one of P    purl(i, j) = i mod 2
seed       ``KPKP…`` then ``PKPK…``   purl(i, j) = (i + j) mod 2
=========  =========================  ==================

or from a chart file: one line a course, the first line the bottom course,
each read from the face left to right as ``K`` and ``P``; lines starting
with ``#`` and blank lines are ignored. Knitting-machine programs (knitout,
``FILE.k``) give theirs through ``knitfem.knit.knitout``.
"""

import os

import numpy as np

from knitfem.errors import KnitError

__all__ = ["Chart", "PATTERNS", "named_chart", "read_chart", "chart_from_spec"]

# purl(i, j) of course i and stitch j, over index grids
PATTERNS = {
    "jersey": lambda i, j: np.zeros_like(i),
    "rib1x1": lambda i, j: j % 2,
    "rib2x2": lambda i, j: (j // 2) % 2,
    "garter": lambda i, j: i % 2,
    "seed": lambda i, j: (i + j) % 2,
}

KNITOUT = (".k", ".knitout")
STITCH = "KP"


class Chart:
    """Knit or purl for each stitch of each course.

    Parameters
    ----------
    purl : array_like of bool, (courses, stitches)
        True where the stitch is a purl as seen from the technical face;
        row 0 is the bottom course, column 0 the left stitch.
    """

    def __init__(self, purl):
        purl = np.array(purl, dtype=bool)
        if purl.ndim != 2 or 0 in purl.shape:
            raise ValueError(f"a chart is a non-empty 2-D grid, not {purl.shape}")
        purl.flags.writeable = False
        self.purl = purl

    @classmethod
    def from_text(cls, lines):
        """The chart of strings of ``K`` and ``P``, the bottom course first."""
        if set("".join(lines)) - set(STITCH):
            raise ValueError(f"a chart's courses are K and P only, not {lines!r}")
        return cls([[c == "P" for c in line] for line in lines])

    @property
    def shape(self):
        """(courses, stitches)."""
        return self.purl.shape

    @property
    def rows(self):
        return self.purl.shape[0]

    @property
    def cols(self):
        return self.purl.shape[1]

    @property
    def jersey(self):
        """Every stitch a knit (plain jersey, stockinette)."""
        return not self.purl.any()

    def text(self):
        """One string of ``K`` and ``P`` a course, the bottom course first
        (what a run's summary reports under ``chart``)."""
        return ["".join(np.take(list(STITCH), row)) for row in self.purl.astype(int)]

    def __eq__(self, other):
        if not isinstance(other, Chart):
            return NotImplemented
        return self.shape == other.shape and bool(np.all(self.purl == other.purl))

    def __hash__(self):
        return hash((self.shape, self.purl.tobytes()))

    def __repr__(self):
        return f"Chart({self.text()!r})"

    def __str__(self):
        """The chart as a chart file writes it: the bottom course first."""
        return "\n".join(self.text())


def named_chart(name, rows, cols):
    """The pattern ``name`` (a key of ``PATTERNS``) over rows × cols stitches."""
    if name not in PATTERNS:
        raise KnitError(f"{name}: not a pattern; use one of {', '.join(PATTERNS)}")
    if rows < 1 or cols < 1:
        raise KnitError(f"{name} {rows}x{cols}: a pattern needs at least one "
                        "course of one stitch")
    i, j = np.indices((rows, cols))
    return Chart(PATTERNS[name](i, j))


def read_chart(path):
    """The chart of a text file: a course a line, bottom first, ``K``/``P``.

    Raises a one-line ``KnitError`` naming the file and the line for a
    character other than K or P, or a course of another length than the
    first one.
    """
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise KnitError(f"{path}: cannot read the chart ({err})") from None
    courses, width = [], None
    for number, raw in enumerate(text, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        bad = sorted(set(line) - set(STITCH))
        if bad:
            raise KnitError(f"{path}:{number}: {''.join(bad)!r} in {line!r}; a "
                            "chart line is K (knit) and P (purl) only, # starts "
                            "a comment line")
        if width is not None and len(line) != width:
            raise KnitError(f"{path}:{number}: a course of {len(line)} stitches "
                            f"where the first had {width}; give every course "
                            "the same number of stitches")
        width = len(line)
        courses.append(line)
    if not courses:
        raise KnitError(f"{path}: no course in the chart; write a line of K and P "
                        "a course, the bottom course first")
    return Chart.from_text(courses)


def chart_from_spec(spec, rows, cols):
    """The chart of a pattern name (sized rows × cols), a chart file, or a
    knitout program (``.k``, ``.knitout``: the knit it makes as a chart)."""
    if spec in PATTERNS:
        return named_chart(spec, rows, cols)
    if not os.path.isfile(spec):
        raise KnitError(f"{spec}: neither a pattern ({'|'.join(PATTERNS)}) nor a "
                        "file (CHART.txt, FILE.k, FILE.knitout)")
    if spec.endswith(KNITOUT):
        from knitfem.knit.knitout import read_knitout

        return read_knitout(spec).chart()
    return read_chart(spec)
