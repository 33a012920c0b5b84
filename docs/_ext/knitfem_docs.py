"""Pages written at build time from what the code and the results say.

``options.md`` includes ``_generated/options.md``: for every command that
``knitfem`` lists, the table of the options its ``-help`` prints (name,
default, help with units), read from the declarations themselves by running
the command line, so the reference cannot drift from the code.
``results.md`` and ``benchmarks.md`` include ``_generated/<study>.md``: a
table a result file of ``benchmarks/results/*.json`` (one row a run found
in it), the command that makes it and its figure.
"""

import glob
import json
import os
import re
import subprocess
import sys

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROOT = os.path.dirname(HERE)
OUT = os.path.join(HERE, "_generated")
RESULTS = os.path.join(ROOT, "benchmarks", "results")
OPTION = re.compile(r"^  (-\S+) <(.*?)>: (.*)$")
COMMAND = re.compile(r"^  ([a-z]+)\s{2,}(\S.*)$")


def knitfem(*args):
    """Output of ``knitfem ARGS`` (the working tree's package)."""
    env = dict(os.environ, PYTHONPATH=ROOT)
    done = subprocess.run([sys.executable, "-m", "knitfem.cli", *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)
    if done.returncode:
        raise RuntimeError(f"knitfem {' '.join(args)}: exit {done.returncode}: "
                           f"{done.stderr.strip()}")
    return done.stdout


def cell(text):
    """Text safe inside a Markdown table cell."""
    return str(text).replace("|", "\\|").replace("*", "\\*")


def commands():
    """(name, description) of every command ``knitfem`` alone lists."""
    found = []
    for line in knitfem().splitlines():
        m = COMMAND.match(line)
        if m:
            found.append(m.groups())
    return found


def options_page():
    """One section a command: its options as -help prints them."""
    lines = []
    for name, text in commands():
        lines += [f"## knitfem {name}", "", f"{text[0].upper()}{text[1:]}.", "",
                  f"`knitfem {name} -help` prints:", "",
                  "| option | default | meaning |", "|---|---|---|"]
        rest = []
        for line in knitfem(name, "-help").splitlines()[1:]:
            m = OPTION.match(line)
            if m:
                opt, default, meaning = m.groups()
                default = f"`{default}`" if default else "(none)"
                lines.append(f"| `{opt}` | {cell(default)} | {cell(meaning)} |")
            elif line.strip():
                rest.append(line)
        lines.append("")
        if rest:
            lines += ["```text", *rest, "```", ""]
    return "\n".join(lines)


def runs(node, path=()):
    """(path, record) of every run a result file holds: a dict with a step
    count and a size or an iteration count; nothing inside a run is
    searched; the "before" runs a study keeps for comparison are left out."""
    if isinstance(node, dict):
        if isinstance(node.get("steps"), int) and (
                {"unknowns", "newton", "newton_iterations"} & set(node)):
            yield path, node
            return
        for key, value in node.items():
            if key not in ("log", "options", "machine", "summary", "before"):
                yield from runs(value, path + (str(key),))
    elif isinstance(node, list):
        for value in node:
            yield from runs(value, path)


def number(value, unit=1.0, digits=4):
    """A figure to ``digits`` significant digits; '' for none (or a record)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return ""
    return f"{value * unit:.{digits}g}"


def columns(path, rec):
    """The table's cells of one run."""
    case = rec.get("forced") or rec.get("options") or {}
    flags = " ".join(f"{k if k.startswith('-') else '-' + k} {v}"
                     for k, v in case.items() if not str(k).startswith("bench"))
    wall = rec.get("wall_s", rec.get("process_s", rec.get("wall_time_s")))
    if isinstance(wall, dict):
        wall = wall.get("total")
    summary = rec.get("summary", rec)
    memory = rec.get("memory", {}).get("peak_rss_mib_max")
    stages = rec.get("stages_s") or {}
    setup = sum(stages.get(k, 0.0) for k in ("Model set-up", "Solver set-up"))
    return [" / ".join(path), rec.get("config", rec.get("model", summary.get("model",
                                                                        ""))),
            flags, rec.get("yarn_control_points", ""),
            rec.get("volume_control_points", ""), rec.get("unknowns", ""),
            number(setup if stages else None, digits=3), rec["steps"],
            rec.get("newton", rec.get("newton_iterations", "")),
            rec.get("rejected", rec.get("rejected_steps", "")),
            number(rec.get("newton_s"), digits=3),
            number(rec.get("error")), number(wall), number(memory, digits=3),
            number(summary.get("drop"), 1e3)]


HEADER = ["case", "model or configuration", "options", "yarn control points",
          "volume control points", "unknowns", "set-up [s]", "steps", "Newton its",
          "rejected", "s a Newton it", "error", "wall [s]", "peak RSS [MiB]",
          "drop [mm]"]


def command_of(name, rec):
    """The command that writes ``name``.json, from the options it recorded."""
    study = rec.get("study")
    if study is None:          # a knitfem run's own summary.json
        model = rec.get("model", "full")
        return (f"knitfem run -knit_scene {rec.get('scene', 'hanging')} -knit_model "
                f"{model} -knit_snapshots 0,0.1,0.4,1,2,3 -knit_animation "
                f"hanging.gif -o out/results_{name}")
    flags = " ".join(f"-{k}" + ("" if v is None else f" {v}")
                     for k, v in (rec.get("options") or {}).items()
                     if k not in ("bench_results", "bench_plot"))
    ranks = rec.get("ranks", 1)
    launch = f"mpirun -n {ranks} " if ranks > 1 else ""
    return (f"{launch}.venv/bin/python -m benchmarks.{study} {flags} "
            "-bench_results benchmarks/results").replace("  ", " ")


def result_page(path):
    """The table, the command and the figure of one result file."""
    name = os.path.splitext(os.path.basename(path))[0]
    with open(path) as f:
        rec = json.load(f)
    rows = [columns(p, r) for p, r in runs(rec)]
    keep = [i for i in range(len(HEADER)) if any(str(r[i]) for r in rows)]
    lines = [f"### {name}", "", "Made by:", "", "```text", command_of(name, rec),
             "```", ""]
    machine = rec.get("machine")
    if isinstance(machine, dict):
        lines += [f"Machine: {machine.get('cpu', '')}, {machine.get('cores', '')} "
                  f"cores, {machine.get('memory_gib', '')} GiB; PETSc "
                  f"{rec.get('petsc', '')}; {rec.get('ranks', 1)} rank(s).", ""]
    if rows:
        lines += ["| " + " | ".join(HEADER[i] for i in keep) + " |",
                  "|" + "---|" * len(keep)]
        lines += ["| " + " | ".join(cell(r[i]) for i in keep) + " |" for r in rows]
        lines.append("")
    figure = os.path.join(RESULTS, "figures", name + ".png")
    if os.path.exists(figure):
        lines += [f"![{name}](../benchmarks/results/figures/{name}.png)", ""]
    return "\n".join(lines)


def generate(app=None):
    """Write _generated/options.md and _generated/<result>.md."""
    os.makedirs(OUT, exist_ok=True)
    pages = {"options.md": options_page()}
    for path in sorted(glob.glob(os.path.join(RESULTS, "*.json"))):
        pages[os.path.basename(path)[:-5] + ".md"] = result_page(path)
    for name, text in pages.items():
        target = os.path.join(OUT, name)
        old = open(target).read() if os.path.exists(target) else None
        if old != text:                  # unchanged pages keep Sphinx's cache
            with open(target, "w") as f:
                f.write(text)


def setup(app):
    app.connect("builder-inited", generate)
    return {"version": "1", "parallel_read_safe": True}


if __name__ == "__main__":
    generate()
