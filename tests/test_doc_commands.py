"""Every command the README and the documentation show is a promise: it
parses as written, writes its own output directory, and the quick ones and
those that name solver options run to the end.
(``benchmarks/doc_commands.py`` runs them all.)"""

import ast
import os
import re
import subprocess
import sys

import pytest
from mpi4py import MPI

from benchmarks.doc_commands import ROOT, doc_commands, environment, output_of

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="runs knitfem in subprocesses")

SHOWN = doc_commands()


def test_commands_are_found_in_the_readme_and_the_docs():
    places = {doc for doc, _ in SHOWN}
    assert "README.md" in places and len(places) >= 6
    assert len(SHOWN) >= 25
    readme = open(os.path.join(ROOT, "README.md")).read()
    assert "source .venv/bin/activate" in readme


def test_every_command_that_writes_has_its_own_output_directory():
    outputs = [output_of(cmd) for _, cmd in SHOWN]
    missing = [cmd for (_, cmd), out in zip(SHOWN, outputs) if out == ""]
    assert not missing, missing
    named = [out for out in outputs if out]
    shared = sorted({out for out in named if named.count(out) > 1})
    assert not shared, shared


SMALLER = ["-knit_rows", "4", "-knit_cols", "4"]
"""What a run of a larger knit that names solver options is run on here: the
options are the same, and they are taken and work (or PETSc warns of them)
whatever the knit's size; benchmarks/doc_commands.py runs it as written."""


@pytest.mark.parametrize("doc,command", SHOWN, ids=[f"{d}:{c[:60]}" for d, c in SHOWN])
def test_command_runs_as_written(tmp_path, doc, command):
    """Its options are known and parse (-help appended); the quick ones, and
    every one that names solver options, run to the end (a knit of more
    than 4x4 on 4x4: ``SMALLER``)."""
    os.symlink(os.path.join(ROOT, "benchmarks"), tmp_path / "benchmarks")
    quick = re.match(r"knitfem( (dofs|pattern)|$)", command)
    solver = re.search(r" -((full|reduced|mixed|static)_|options_file )", command)
    size = [int(n) for n in re.findall(r"-knit_(?:rows|cols) (\d+)", command)]
    smaller = SMALLER if solver and not quick and max(size, default=0) > 4 else []
    for run_it in (False, True) if quick or solver else (False,):
        p = subprocess.run(command.split() + (smaller if run_it else ["-help"])
                           + ["-skip_petscrc"], capture_output=True, text=True,
                           env=environment(), cwd=tmp_path, timeout=300,
                           stdin=subprocess.DEVNULL)
        assert p.returncode == 0, (command, p.stderr)
        assert "unknown" not in p.stderr and "warning" not in p.stderr, command


def test_garment_runs_shown_are_the_benchmarks_commands():
    """The tube, sleeve, elbow and drape runs take minutes: each is one of
    ``benchmarks/garments.py``'s COMMANDS, which that study runs as written."""
    tree = ast.parse(open(os.path.join(ROOT, "benchmarks", "garments.py")).read())
    commands = next(ast.literal_eval(node.value) for node in tree.body
                    if isinstance(node, ast.Assign)
                    and node.targets[0].id == "COMMANDS")
    garments = [cmd for _, cmd in SHOWN if cmd.startswith("knitfem run")
                and ("-knit_shape tube" in cmd or "-knit_scene drape" in cmd
                     or "-knit_scene sleeve" in cmd)]
    assert len(garments) >= 3
    assert set(garments) <= set(commands.values())


PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.M | re.S)


def python_snippets():
    """(document, code) of the Python blocks shown that use the API."""
    from benchmarks.doc_commands import documents

    return [(os.path.relpath(path, ROOT), code) for path in documents()
            for code in PYTHON_BLOCK.findall(open(path).read())
            if "import knitfem" in code]


@pytest.mark.parametrize("doc,code", python_snippets(),
                         ids=[d for d, _ in python_snippets()])
def test_python_snippet_runs_as_written(tmp_path, doc, code):
    script = tmp_path / "snippet.py"
    script.write_text(code)
    p = subprocess.run([sys.executable, str(script), "-skip_petscrc"],
                       capture_output=True, text=True, env=environment(),
                       cwd=tmp_path, timeout=300)
    assert p.returncode == 0, (doc, p.stderr[-2000:])
    assert (tmp_path / "out").is_dir()
