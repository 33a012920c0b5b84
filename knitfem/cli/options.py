"""Our -knit_ options: each declared once with a default and a help line.

PETSc's own getters register no help text and raise tracebacks on a value
that does not parse; ``KnitOptions`` reads every value as a string, parses
it, and turns bad input into a one-line ``KnitError`` naming the option and
what it accepts. Once a command has declared its options, ``finish`` prints
them under ``-help`` (the command then stops) or refuses an option of ours
that nobody declared, naming the nearest declared one; ``unused_options``
lists the PETSc options nothing read, for a warning at the end.
"""

import ctypes
import difflib
from typing import NamedTuple

import numpy as np
from petsc4py import PETSc

from knitfem.errors import KnitError
from solvers.libpetsc import Int, library

__all__ = ["KnitError", "KnitOptions", "Declaration", "declarations",
           "unused_options"]

OURS = ("knit_", "bench_")


class Declaration(NamedTuple):
    """One option as a command declares it: ``-{name} <{default}>: {text}``."""

    name: str
    default: str
    text: str

    def __str__(self):
        return f"  -{self.name} <{self.default}>: {self.text}"


class KnitOptions:
    """Our -knit_ options, each with a default and a help line.

    ``declared`` holds every option name any instance declared in this
    process; ``help`` is set by the command line (``knitfem CMD -help``);
    ``catalogue``, a list, collects a command's declarations instead of
    printing them under help (``declarations``).
    """

    declared = set()
    help = False
    catalogue = None

    def __init__(self, prefix="knit_"):
        self.db, self.prefix, self.entries = PETSc.Options(prefix), prefix, []

    def _declare(self, name, default, text):
        if all(e.name != name for e in self.entries):   # shared by several scenes
            self.entries.append(Declaration(name, str(default), text))

    def _raw(self, name, default, text):
        self._declare(self.prefix + name, default, text)
        KnitOptions.declared.add(self.prefix + name)
        if not self.db.hasName(name):
            return None
        return self.db.getString(name, "")

    def _fail(self, name, value, wants):
        raise KnitError(f"-{self.prefix}{name} {value!r}: expected {wants}")

    def getInt(self, name, default, text, minimum=None):
        """An integer, at least ``minimum`` when given."""
        raw = self._raw(name, default, text)
        if raw is None:
            return default
        try:
            value = int(raw)
        except ValueError:
            self._fail(name, raw, "an integer")
        if minimum is not None and value < minimum:
            self._fail(name, raw, f"an integer >= {minimum}")
        return value

    def getReal(self, name, default, text, positive=False, nonnegative=False):
        """A real number, optionally > 0 or >= 0."""
        raw = self._raw(name, default, text)
        if raw is None:
            return default
        try:
            value = float(raw)
        except ValueError:
            self._fail(name, raw, "a real number")
        if value != value or abs(value) == float("inf"):
            self._fail(name, raw, "a finite real number")
        if positive and value <= 0:
            self._fail(name, raw, "a positive real number")
        if nonnegative and value < 0:
            self._fail(name, raw, "a non-negative real number")
        return value

    def getInts(self, name, default, text, count, minimum=None):
        """``count`` comma-separated integers, e.g. ``-knit_lod 5,5``."""
        wants = f"{count} comma-separated integers" + (
            f" >= {minimum}" if minimum is not None else "")
        value = self._numbers(name, default, text, count, int, wants)
        if minimum is not None and min(value) < minimum:
            self._fail(name, ",".join(map(str, value)), wants)
        return value

    def getReals(self, name, default, text, count):
        """``count`` comma-separated finite reals, e.g. ``-knit_start_rotation
        0,45,0``."""
        value = self._numbers(name, default, text, count, float,
                              f"{count} comma-separated real numbers")
        if not np.all(np.isfinite(value)):
            self._fail(name, ",".join(map(str, value)), "finite real numbers")
        return value

    def _numbers(self, name, default, text, count, kind, wants):
        raw = self._raw(name, ",".join(f"{v:g}" if kind is float else str(v)
                                       for v in default), text)
        if raw is None:
            return tuple(default)
        try:
            value = tuple(kind(v) for v in raw.split(","))
        except ValueError:
            self._fail(name, raw, wants)
        if len(value) != count:
            self._fail(name, raw, wants)
        return value

    def getChoice(self, name, default, choices, text):
        """One of ``choices``."""
        raw = self._raw(name, default, f"{text} ({'|'.join(choices)})")
        if raw is None:
            return default
        if raw not in choices:
            self._fail(name, raw, "one of " + ", ".join(choices))
        return raw

    def getBool(self, name, default, text):
        """A flag: present alone means true; also accepts true/false, 1/0."""
        raw = self._raw(name, default, text)
        if raw is None:
            return default
        table = {"": True, "1": True, "true": True, "yes": True,
                 "0": False, "false": False, "no": False}
        if raw.lower() not in table:
            self._fail(name, raw, "true or false")
        return table[raw.lower()]

    def getString(self, name, default, text):
        """Any string (a file name, say)."""
        raw = self._raw(name, default, text)
        return default if raw is None else raw

    def getOutput(self, default, shown=None):
        """The output directory, ``-o DIR`` (no prefix); ``shown``: the
        default as -help gives it, where it depends on other options."""
        self._declare("o", shown or default, "output directory")
        KnitOptions.declared.add("o")
        return PETSc.Options().getString("o", default)

    @staticmethod
    def helping():
        """The command only lists its options (-help, or ``declarations``):
        option values name files that need not exist."""
        return (KnitOptions.help or KnitOptions.catalogue is not None
                or PETSc.Options().hasName("help"))

    def printHelp(self, title):
        """Under -help, print the declared options (collective), or add them
        to ``catalogue``. True if it did."""
        if KnitOptions.catalogue is not None:
            KnitOptions.catalogue.extend(self.entries)
            return True
        if self.helping():
            PETSc.Sys.Print(f"{title} options:\n" + "\n".join(map(str, self.entries)))
            return True
        return False

    def finish(self, title, footer=""):
        """After the last declaration: refuse an option of ours (-knit_*,
        -bench_*) that was not declared; under -help print the options and
        ``footer`` and return True (the command stops)."""
        unknown = sorted(k for k in PETSc.Options().getAll()
                         if k.startswith(OURS) and k not in KnitOptions.declared)
        if unknown:
            name = unknown[0]
            near = difflib.get_close_matches(name, sorted(KnitOptions.declared), 1)
            hint = f"; did you mean -{near[0]}?" if near else ""
            raise KnitError(f"unknown option -{name}{hint} ({title} -help lists "
                            "the options)")
        if self.printHelp(title):
            if footer and KnitOptions.catalogue is None:
                PETSc.Sys.Print(footer)
            return True
        return False


def unused_options():
    """Names of the options in PETSc's database that nothing has read
    (PetscOptionsLeftGet; empty where the symbol cannot be found)."""
    try:
        lib = library()
        get, restore = lib.PetscOptionsLeftGet, lib.PetscOptionsLeftRestore
    except (OSError, AttributeError):
        return []
    n = Int()
    names, values = (ctypes.POINTER(ctypes.c_char_p)() for _ in range(2))
    args = (None, ctypes.byref(n), ctypes.byref(names), ctypes.byref(values))
    if get(*args):
        return []
    left = [names[i].decode() for i in range(n.value)]
    restore(*args)
    return left


def declarations(command):
    """The options ``knitfem <command>`` declares, in order (a list of
    ``Declaration``), as its -help lists them; the command stops before it
    runs. Collective; PETSc must be initialised."""
    from knitfem.cli import commands

    KnitOptions.catalogue = []
    try:
        getattr(commands, command)(PETSc.COMM_WORLD)
        return KnitOptions.catalogue
    finally:
        KnitOptions.catalogue = None
