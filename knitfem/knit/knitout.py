"""Knitting-machine programs (knitout) read into a knit graph.

Knitout (McCann et al. 2016; the CMU textiles lab's specification, v0.6) is
a line-oriented list of needle operations on a V-bed machine: a front bed
``f`` and a back bed ``b`` (with sliders ``fs``, ``bs``), the back bed racked
by R so that back needle B faces front needle B + R, and yarn carriers that
are brought in, knit, tuck, split, miss and go out. ``read_knitout`` runs a
program on a model of that machine (the loops each needle holds) and returns
the ``KnitGraph`` it knits: every loop with the loops it was pulled through
(its parents), the yarn of each carrier as one sequence of loops, and, where
the knit is a plain grid of knits and purls, its ``Chart``.

Why our own reader and not PyPI's ``knitout-interpreter`` (which would
leave Debian's numpy alone): the machine model needed here is small (two
beds of needle → loops, a racking, the carriers in action; a dozen
operations), while the interpreter 0.1.8 brings eight more packages to pin
(knit-graphs 0.1.4, virtual-knitting-machine 0.0.31, parglare, networkx 3.6
over the Debian 2.8 the rest of the system sees, click, svgwrite, webcolors,
importlib_resources), young ones whose graphs we would still translate into
loops, courses and wale positions of our own. Our reader has no dependency
beyond numpy, follows the specification's reading rules (unknown headers
and extensions warned about and ignored), and reports every bad line as one
``KnitError`` naming the file and the line.

What the graph records (all as seen from the technical face, the front bed's
side): a loop's stitch is ``K`` for a knit or split on the front bed, ``P``
on the back bed (a purl is a loop knitted on the back bed, e.g. after a
transfer), ``T`` for a tuck (a loop added to the needle's others) and ``M``
for a miss (the yarn floats past the needle; nothing is held). Its wale
position is its needle's place on the front bed's scale at the time it was
made: front needle n at n, back needle n at n + R. A course is one pass of a
carrier set: it ends where the carriers turn or jump back. Courses whose
loops all have no parent (the cast-on) are not counted in the chart.
"""

import math
import re
import warnings
from dataclasses import dataclass, field

import numpy as np

from knitfem.errors import KnitError
from knitfem.knit.chart import Chart

__all__ = ["KnitoutWarning", "Loop", "Course", "KnitGraph", "read_knitout",
           "parse_knitout"]

NEEDLE = re.compile(r"(fs|bs|f|b)(-?\d+)$")
MAGIC = re.compile(r";!knitout-(\d+)\s*$")
HEADER = re.compile(r";;([^:]+):\s?(.*)$")
VERSION = 2
HEADERS = ("Machine", "Gauge", "Carriers", "Position", "Width")

# parameters of each operation: D direction, N needle, R real number,
# CS carriers (possibly none), CS+ at least one carrier
SIGNATURES = {
    "in": "CS+", "inhook": "CS+", "releasehook": "CS+", "out": "CS+",
    "outhook": "CS+", "stitch": "R R", "rack": "R", "pause": "",
    "knit": "D N CS", "tuck": "D N CS", "split": "D N N CS", "miss": "D N CS+",
    "drop": "N", "amiss": "N", "xfer": "N N",
}
MEANING = {"D": "a direction + or -", "N": "a needle such as f3, b-2 or fs1",
           "R": "a number", "CS": "carriers", "CS+": "one or more carriers"}


class KnitoutWarning(UserWarning):
    """A knitout file readable but not standard, or an extension ignored."""


class BadLine(Exception):
    """What is wrong with the line being run (becomes a ``KnitError``)."""


@dataclass(frozen=True)
class Loop:
    """One loop (or, for a miss, one float) a carrier set made.

    ``parents`` are the ids of the loops it was pulled through: one for a
    plain knit, two for a decrease, none for a cast-on loop, a tuck, a
    yarn-over or a float. ``line`` is the program line that made it.
    """

    id: int
    carriers: tuple
    course: int
    position: float
    needle: str
    stitch: str
    parents: tuple
    line: int

    @property
    def bed(self):
        """``f``, ``b``, ``fs`` or ``bs``."""
        return NEEDLE.match(self.needle).group(1)


@dataclass
class Course:
    """One pass of a carrier set in one direction: its loops in order."""

    index: int
    carriers: tuple
    direction: str
    loops: list = field(default_factory=list)


@dataclass
class KnitGraph:
    """The knit a program makes.

    Attributes
    ----------
    loops : list of Loop, by id (the order they were made)
    courses : list of Course, in the order they began
    yarns : dict carrier → list of loop ids, that carrier's one yarn
    held : dict needle → loop ids still on it when the program ends
    headers : dict of the comment header (``;;Key: value``)
    source : the file name, for messages
    """

    loops: list
    courses: list
    yarns: dict
    held: dict
    headers: dict
    source: str

    def knitted(self):
        """The courses with a loop pulled through another (not the cast-on)."""
        return [c for c in self.courses
                if any(self.loops[i].parents for i in c.loops)]

    def drawing(self):
        """The knitted courses, one string a course (bottom first), one
        symbol a wale position (left to right): ``K``/``P`` a knit/purl,
        ``T`` a tuck, ``-`` a float, ``O`` a yarn-over (a knit through no
        loop), ``X`` a decrease (through two or more), ``*`` several loops at
        one wale, ``.`` none."""
        return ["".join(row) for row in self.cells()[0]]

    def cells(self):
        """The drawing's symbols (courses, wales) and, for each, the first
        loop drawn there (None where there is none)."""
        courses = self.knitted()
        if not courses:
            raise KnitError(f"{self.source}: no knitted course (only cast-on "
                            "loops); knit at least one course over them")
        loops = [[self.loops[i] for i in c.loops] for c in courses]
        wales = sorted({lp.position for course in loops for lp in course})
        column = {x: j for j, x in enumerate(wales)}
        grid = np.full((len(loops), len(wales)), ".")
        first = np.full(grid.shape, None, dtype=object)
        for r, course in enumerate(loops):
            for lp in course:
                j = column[lp.position]
                grid[r, j] = symbol(lp) if first[r, j] is None else "*"
                first[r, j] = first[r, j] or lp
        return grid, first, wales

    def chart(self):
        """The knitted courses as a chart of knits and purls.

        Raises ``KnitError`` where the knit is not a plain grid (a symbol of
        ``drawing`` other than K and P), naming the first such place.
        """
        grid, first, wales = self.cells()
        odd = np.argwhere((grid != "K") & (grid != "P"))
        if len(odd):
            r, j = odd[0]
            lp = first[r, j]
            where = (f"{self.source}: no stitch at wale position {wales[j]:g}"
                     if lp is None else f"{self.source}:{lp.line}: "
                     f"{SYMBOLS[grid[r, j]]} at {lp.needle}")
            raise KnitError(f"{where} in knitted course {r}; only a plain grid of "
                            "knits and purls makes a chart")
        return Chart(grid == "P")


SYMBOLS = {"T": "a tuck", "-": "a float (miss)", "O": "a yarn-over",
           "X": "a decrease", "*": "several loops at one wale"}


def symbol(loop):
    """The drawing's symbol of one loop."""
    if loop.stitch in "TM":
        return "T" if loop.stitch == "T" else "-"
    return loop.stitch if len(loop.parents) == 1 else "X" if loop.parents else "O"


class Machine:
    """A V-bed machine running knitout: needles holding loops, a racking,
    carriers in action, and the knit graph being made."""

    def __init__(self, headers):
        self.line = 0
        names = re.split(r"[\s,;]+", headers.get("Carriers", "").strip())
        self.known = set(filter(None, names)) or None
        self.rack = 0.0
        self.active = set()
        self.held = {}
        self.loops, self.courses, self.yarns = [], [], {}
        self.passes = {}            # carriers → (course, direction, position)

    # parameters

    def parse(self, opcode, args):
        """Parameters of ``opcode`` converted as its signature says."""
        kinds = SIGNATURES[opcode].split()
        wants = " ".join(kinds)
        out = []
        for i, kind in enumerate(kinds):
            if kind.startswith("CS"):
                carriers = tuple(args[i:])
                if kind == "CS+" and not carriers:
                    raise BadLine(f"{opcode} needs {MEANING[kind]} ({wants})")
                return out + [self.carriers(carriers)]
            if i >= len(args):
                raise BadLine(f"{opcode} needs {len(kinds)} parameters ({wants})")
            out.append(self.value(kind, args[i]))
        if len(args) > len(kinds):
            raise BadLine(f"{opcode} takes {len(kinds)} parameters ({wants or 'none'})")
        return out

    def value(self, kind, token):
        """``token`` as a parameter of kind D, N or R."""
        if kind == "D" and token in ("+", "-"):
            return token
        if kind == "N" and NEEDLE.match(token):
            return token
        if kind == "R":
            try:
                x = float(token)
            except ValueError:
                x = math.nan
            if math.isfinite(x):
                return x
        raise BadLine(f"{token!r} is not {MEANING[kind]}")

    def carriers(self, names):
        """The carrier set ``names``, each one the ;;Carriers header names."""
        unknown = [c for c in names if self.known and c not in self.known]
        if unknown:
            raise BadLine(f"carrier {unknown[0]} is not in the ;;Carriers header "
                          f"({' '.join(sorted(self.known))})")
        return names

    # carriers

    def op_in(self, cs):
        if self.active & set(cs):
            raise BadLine(f"carrier {min(self.active & set(cs))} is already in")
        self.active |= set(cs)

    op_inhook = op_in

    def op_out(self, cs):
        if set(cs) - self.active:
            raise BadLine(f"carrier {min(set(cs) - self.active)} is not in; bring "
                          "it in (in/inhook) before taking it out")
        self.active -= set(cs)
        for c in cs:
            self.passes = {k: v for k, v in self.passes.items() if c not in k}

    op_outhook = op_out

    def op_releasehook(self, cs):
        pass

    # machine settings

    def op_rack(self, r):
        self.rack = r

    def op_stitch(self, before, after):
        pass

    def op_pause(self):
        pass

    # needle operations

    def op_knit(self, d, n, cs):
        parents = tuple(self.held.pop(n, ()))
        if cs:
            self.held[n] = [self.loop(d, n, cs, self.face(n), parents)]

    def op_tuck(self, d, n, cs):
        if cs:
            self.face(n)
            self.held.setdefault(n, []).append(self.loop(d, n, cs, "T", ()))

    def op_split(self, d, n, n2, cs):
        if {side(n), side(n2)} != {"f", "b"}:
            raise BadLine(f"{n} and {n2} are not on opposite beds")
        f, b = (n, n2) if side(n) == "f" else (n2, n)
        if index(f) - index(b) != self.rack:
            raise BadLine(f"{n} and {n2} do not face each other at racking "
                          f"{self.rack:g} (back needle B faces front needle B + R)")
        parents = self.held.pop(n, [])
        self.held.setdefault(n2, []).extend(parents)
        if cs:
            self.held[n] = [self.loop(d, n, cs, self.face(n), tuple(parents))]

    def op_miss(self, d, n, cs):
        self.loop(d, n, cs, "M", ())

    def op_drop(self, n):
        self.op_knit("+", n, ())

    def op_amiss(self, n):
        pass

    def op_xfer(self, n, n2):
        self.op_split("+", n, n2, ())

    # the graph

    def face(self, n):
        """The stitch a loop pulled through on needle n shows on the face."""
        if bed(n) != side(n):
            raise BadLine(f"{n} is a slider: it holds transferred loops, it "
                          "does not knit")
        return "K" if bed(n) == "f" else "P"

    def loop(self, d, n, cs, stitch, parents):
        """Record a new loop of carriers ``cs`` on needle n, in its course."""
        idle = set(cs) - self.active
        if idle:
            raise BadLine(f"carrier {min(idle)} is not in; bring it in with "
                          f"'in {min(idle)}' or 'inhook {min(idle)}' first")
        x = index(n) + (self.rack if side(n) == "b" else 0.0)
        last = self.passes.get(cs)
        sign = 1 if d == "+" else -1
        if last is None or last[1] != d or (x - last[2]) * sign < 0:
            course = Course(len(self.courses), cs, d)
            self.courses.append(course)
        else:
            course = self.courses[last[0]]
        self.passes[cs] = (course.index, d, x)
        lp = Loop(len(self.loops), cs, course.index, x, n, stitch, parents, self.line)
        self.loops.append(lp)
        course.loops.append(lp.id)
        for c in cs:
            self.yarns.setdefault(c, []).append(lp.id)
        return lp.id


def bed(needle):
    return NEEDLE.match(needle).group(1)


def index(needle):
    return int(NEEDLE.match(needle).group(2))


def side(needle):
    """``f`` for the front bed and its sliders, ``b`` for the back."""
    return needle[0]


def read_knitout(path):
    """The knit graph of the knitout program in file ``path``."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as err:
        raise KnitError(f"{path}: cannot read the knitout program ({err})") from None
    return parse_knitout(text, path)


def parse_knitout(text, source="<knitout>"):
    """The knit graph of a knitout program's text.

    Unknown headers, ``X-`` headers and ``x-`` operations are warned about
    (``KnitoutWarning``, once each) and ignored, as the specification asks;
    a line the machine cannot run is a one-line ``KnitError`` naming
    ``source`` and the line.
    """
    warned = set()

    def warn(key, message, number):
        if key not in warned:
            warned.add(key)
            warnings.warn_explicit(message, KnitoutWarning, source, number)

    lines = text.splitlines()
    magic = MAGIC.match(lines[0]) if lines else None
    if magic is None:
        warn("magic", "no ';!knitout-2' first line; read as knitout anyway", 1)
    elif int(magic.group(1)) > VERSION:
        warn("magic", f"knitout-{magic.group(1)} is newer than knitout-{VERSION}; "
             "read as knitout-2", 1)
    headers, start = {}, 1 if magic else 0
    while start < len(lines) and lines[start].startswith(";;"):
        match = HEADER.match(lines[start])
        key = match.group(1).strip() if match else lines[start]
        if match and (key in HEADERS or key.startswith("Yarn-")):
            headers[key] = match.group(2).strip()
        else:
            warn(("header", key), f"header {key!r} not known; ignored", start + 1)
        start += 1
    if "Carriers" not in headers:
        warn("carriers", "no ;;Carriers header; every carrier name is accepted", 1)
    machine = Machine(headers)
    for number in range(start + 1, len(lines) + 1):
        op = lines[number - 1].split(";", 1)[0].split()
        if not op:
            continue
        if op[0].startswith("x-"):
            warn(("x", op[0]), f"extension {op[0]!r} not supported; ignored", number)
            continue
        if op[0] not in SIGNATURES:
            raise KnitError(f"{source}:{number}: unknown operation {op[0]!r}; "
                            f"knitout has {', '.join(SIGNATURES)} and x- extensions")
        machine.line = number
        try:
            getattr(machine, "op_" + op[0])(*machine.parse(op[0], op[1:]))
        except BadLine as err:
            raise KnitError(f"{source}:{number}: {' '.join(op)}: {err}") from None
    held = {n: tuple(ids) for n, ids in machine.held.items() if ids}
    return KnitGraph(machine.loops, machine.courses, machine.yarns, held,
                     headers, source)
