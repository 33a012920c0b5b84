"""Every command the README and the documentation show, run as written.

    .venv/bin/python -m benchmarks.doc_commands               # run them all
    .venv/bin/python -m benchmarks.doc_commands -bench_match drape
    .venv/bin/python -m benchmarks.doc_commands -bench_list   # list them only

A command is a line of a code block (no language, ``text``, ``sh`` or
``bash``) of README.md or docs/**/*.md that starts with ``knitfem`` or
``mpirun -n N knitfem``; a trailing ``\\`` continues it, a ``  #`` starts a
comment. Each runs from the repository root with ``.venv/bin`` first on the
PATH, one after the other (some take minutes: the full drape about 7); the
study prints one line a command (exit status, wall time) and writes
<results>/doc_commands.json. ``tests/test_doc_commands.py`` checks the
quick half of this promise on every test run: each command parses (its
options are known: ``-help`` appended exits 0) and writes its own ``-o``.
"""

import glob
import os
import re
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHELL_BLOCK = re.compile(r"^```(?:text|sh|bash)?\n(.*?)^```", re.M | re.S)
COMMAND = re.compile(r"^(mpirun -n \d+ )?knitfem(\s|$)")
WRITERS = ("pattern", "run", "deform")
"""The commands that write files, each into its -o directory."""


def documents(root=ROOT):
    """README.md and the documentation's Markdown sources."""
    docs = sorted(glob.glob(os.path.join(root, "docs", "**", "*.md"), recursive=True))
    return [os.path.join(root, "README.md")] + [
        d for d in docs if not os.path.relpath(d, root).startswith(
            ("docs/_build", "docs/_generated"))]


def commands_in(text):
    """The knitfem command lines of the shell code blocks of ``text``."""
    found = []
    for block in SHELL_BLOCK.findall(text):
        for line in block.replace("\\\n", " ").splitlines():
            line = " ".join(re.sub(r"\s+#.*$", "", line).split())
            if COMMAND.match(line):
                found.append(line)
    return found


def doc_commands(root=ROOT):
    """(document, command) of every command shown, in document order."""
    return [(os.path.relpath(path, root), cmd) for path in documents(root)
            for cmd in commands_in(open(path).read())]


def output_of(command):
    """The -o directory of a command that writes files; None for one that
    does not (dofs, help); '' for a writer that names none."""
    words = command.split()
    knitfem = words.index("knitfem")
    sub = words[knitfem + 1] if len(words) > knitfem + 1 else ""
    if sub not in WRITERS or "-help" in words:
        return None
    return words[words.index("-o") + 1] if "-o" in words else ""


def environment():
    """The environment of a shell that sourced .venv/bin/activate, allowed
    to run mpirun as root on an oversubscribed machine."""
    return dict(os.environ, PATH=os.path.dirname(sys.executable) + os.pathsep
                + os.environ["PATH"], OMPI_ALLOW_RUN_AS_ROOT="1",
                OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                OMPI_MCA_rmaps_base_oversubscribe="1")


def main():
    from .common import KnitOptions, PETSc, write_json

    opts = KnitOptions("bench_")
    listing = opts.getBool("list", False, "list the commands, run nothing")
    match = opts.getString("match", "", "run only the commands containing this text")
    if opts.finish("benchmarks.doc_commands"):
        return
    shown = [(doc, cmd) for doc, cmd in doc_commands() if match in cmd]
    results = []
    for doc, cmd in shown:
        if listing:
            PETSc.Sys.Print(f"{doc}: {cmd}")
            continue
        start = time.perf_counter()
        done = subprocess.run(cmd.split(), cwd=ROOT, env=environment(),
                              capture_output=True, text=True)
        wall = time.perf_counter() - start
        last = (done.stderr.strip() or done.stdout.strip()).splitlines()[-1:] or [""]
        results.append(dict(document=doc, command=cmd, exit=done.returncode,
                            wall_s=wall, last_line=last[0]))
        PETSc.Sys.Print(f"exit {done.returncode}  {wall:7.1f} s  {cmd}")
    if results:
        write_json("doc_commands", dict(study="doc_commands", runs=results))
        failed = [r["command"] for r in results if r["exit"]]
        PETSc.Sys.Print(f"{len(results) - len(failed)} of {len(results)} commands "
                        "exited 0" + "".join(f"\n  failed: {c}" for c in failed))


if __name__ == "__main__":
    main()
