"""Knitting-machine programs read into knit graphs (``knitfem.knit.knitout``)."""

import os
import warnings

import pytest

from knitfem.errors import KnitError
from knitfem.knit.chart import chart_from_spec, named_chart
from knitfem.knit.knitout import KnitoutWarning, parse_knitout, read_knitout

RIB = os.path.join(os.path.dirname(__file__), "data", "rib1x1_10x12.k")
HEADER = [";!knitout-2", ";;Machine: SWG091N2", ";;Carriers: 1 2 3"]


def program(*ops, header=HEADER):
    """A knitout program's text from lines or lists of lines."""
    lines = list(header)
    for op in ops:
        lines += [op] if isinstance(op, str) else op
    return "\n".join(lines) + "\n"


def caston(needles, bed="f"):
    """Carrier 3 in, a loop tucked on each needle, right to left."""
    return (["inhook 3"] + [f"tuck - {bed}{n} 3" for n in sorted(needles)[::-1]]
            + ["releasehook 3"])


def course(needles, d="+", bed="f"):
    """A pass of knits of carrier 3 (needles in order of direction d)."""
    order = sorted(needles, key=lambda n: int(n[1:]) if isinstance(n, str) else n,
                   reverse=d == "-")
    return [f"knit {d} {n if isinstance(n, str) else bed + str(n)} 3" for n in order]


def read(text):
    with warnings.catch_warnings():
        warnings.simplefilter("error", KnitoutWarning)
        return parse_knitout(text, "t.k")


def test_the_machine_rib_is_twelve_courses_of_knit_purl():
    with warnings.catch_warnings():
        warnings.simplefilter("error", KnitoutWarning)   # ;;Width: is known
        chart_source = chart_from_spec(RIB, 1, 1)
        graph = read_knitout(RIB)
    assert chart_source == named_chart("rib1x1", 12, 10)
    assert chart_source.text() == ["KPKPKPKPKP"] * 12
    assert len(graph.courses) == 13 and graph.headers["Width"] == "250"
    caston_loops = [graph.loops[i] for i in graph.courses[0].loops]
    assert {lp.stitch for lp in caston_loops} == {"T"}
    assert all(not lp.parents for lp in caston_loops)
    # one continuous yarn; every knitted loop pulled through the one below it
    assert graph.yarns["3"] == list(range(len(graph.loops))) == list(range(130))
    for lp in graph.loops[10:]:
        (parent,) = lp.parents
        assert graph.loops[parent].position == lp.position
        assert graph.loops[parent].course == lp.course - 1
        assert lp.stitch == ("K" if lp.bed == "f" else "P")
    assert sorted(graph.held) == sorted(f"{'fb'[n % 2]}{n}" for n in range(10))


def test_jersey_on_negative_needles():
    text = program(caston(range(-3, 2)), course(range(-3, 2)),
                   course(range(-3, 2), "-"), course(range(-3, 2)), "outhook 3")
    graph = read(text)
    assert graph.chart() == named_chart("jersey", 3, 5)
    assert [graph.loops[i].needle for i in graph.courses[1].loops] == [
        "f-3", "f-2", "f-1", "f0", "f1"]
    assert [graph.loops[i].position for i in graph.courses[1].loops] == [
        -3, -2, -1, 0, 1]


def test_garter_by_transfers_knits_purl_courses_on_the_back_bed():
    n = range(4)
    to_back = [f"xfer f{i} b{i}" for i in n]
    to_front = [f"xfer b{i} f{i}" for i in n]
    text = program(caston(n), course(n), to_back, course(n, "-", "b"), to_front,
                   course(n), to_back, course(n, "-", "b"))
    graph = read(text)
    assert graph.chart() == named_chart("garter", 4, 4)
    # the purl loops were pulled through the transferred knit loops
    purl = graph.loops[graph.courses[2].loops[0]]
    assert purl.needle == "b3" and graph.loops[purl.parents[0]].needle == "f3"


def test_all_needle_rib_at_quarter_racking():
    n = range(4)
    knit = [f"knit + {b}{i} 3" for i in n for b in "fb"]
    text = program("rack +0.25", caston(n), [f"tuck + b{i} 3" for i in n], knit,
                   [k.replace("+", "-") for k in knit[::-1]])
    graph = read(text)
    # every front needle n at n, every back needle n faces n + 0.25
    assert graph.chart().text() == ["KP" * 4] * 2
    assert graph.loops[graph.courses[2].loops[1]].position == 0.25
    assert len(graph.loops[graph.courses[2].loops[0]].parents) == 1


def with_middle(op):
    """Three stitches over three courses, the second course's middle one made
    by ``op`` (tuck, miss) on f1."""
    n = range(3)
    return read(program(caston(n), course(n), "knit - f2 3", f"{op} - f1 3",
                        "knit - f0 3", course(n)))


def test_a_tuck_is_held_with_the_loop_and_knitted_off_with_it():
    graph = with_middle("tuck")
    tuck = graph.loops[graph.courses[2].loops[1]]
    assert tuck.stitch == "T" and tuck.parents == () and tuck.needle == "f1"
    above = graph.loops[graph.courses[3].loops[1]]
    below = graph.loops[graph.courses[1].loops[1]]
    assert above.parents == (below.id, tuck.id)
    assert graph.drawing() == ["KKK", "KTK", "KXK"]
    with pytest.raises(KnitError, match=r"^t\.k:13: a tuck at f1 in knitted course 1"):
        graph.chart()


def test_a_miss_floats_the_yarn_past_a_held_loop():
    graph = with_middle("miss")
    float_ = graph.loops[graph.courses[2].loops[1]]
    assert float_.stitch == "M" and float_.id in graph.yarns["3"]
    assert float_.id not in sum(graph.held.values(), ())
    # the loop above the float is pulled through the loop two courses down
    above = graph.loops[graph.courses[3].loops[1]]
    assert above.parents == (graph.courses[1].loops[1],)
    assert graph.drawing() == ["KKK", "K-K", "KKK"]
    with pytest.raises(KnitError, match="a float"):
        graph.chart()


def test_a_decrease_by_transfer_with_racking_and_a_yarn_over():
    n = range(5)
    text = program(caston(n), course(n), "xfer f2 b2", "rack +1", "xfer b2 f3",
                   "rack 0", course(n, "-"))
    graph = read(text)
    first = {graph.loops[i].needle: i for i in graph.courses[1].loops}
    top = {graph.loops[i].needle: graph.loops[i] for i in graph.courses[2].loops}
    assert top["f3"].parents == (first["f3"], first["f2"])     # two parents
    assert top["f2"].parents == ()                             # the yarn-over
    assert top["f1"].parents == (first["f1"],)
    assert graph.drawing() == ["KKKKK", "KKOXK"]
    with pytest.raises(KnitError, match=r"t\.k:22: a yarn-over at f2 in knitted "
                       "course 1"):
        graph.chart()


def test_split_knits_a_loop_and_moves_the_old_ones_across():
    text = program(caston(range(2)), course(range(2)), "split - f1 b1 3",
                   "knit - f0 3")
    graph = read(text)
    new = graph.loops[graph.courses[2].loops[0]]
    assert new.needle == "f1" and new.parents == (graph.courses[1].loops[1],)
    assert graph.held["b1"] == new.parents and graph.held["f1"] == (new.id,)


def test_drop_amiss_and_an_empty_split_hold_what_the_spec_says():
    n = range(3)
    graph = read(program(caston(n), course(n), "amiss f1", "drop f0",
                         "split + f2 b2", "outhook 3"))
    top = graph.courses[1].loops
    assert graph.held == {"f1": (top[1],), "b2": (top[2],)}
    assert len(graph.loops) == 6                     # amiss and drop make none


def test_unknown_headers_and_extensions_are_warned_once_and_ignored():
    header = HEADER + [";;X-Presser: on", ";;Frobnication: 3", ";;X-Presser: off"]
    text = program(caston(range(2)), "x-presser-mode auto", course(range(2)),
                   "x-presser-mode off", "x-speed-number 300 ;speed", "pause",
                   "stitch 30 -7.5", course(range(2), "-"), header=header)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        graph = parse_knitout(text, "t.k")
    messages = sorted(str(w.message) for w in said)
    assert len(messages) == 4 and all(w.category is KnitoutWarning for w in said)
    assert sum("X-Presser" in m for m in messages) == 1
    assert sum("x-presser-mode" in m for m in messages) == 1
    assert graph.chart() == named_chart("jersey", 2, 2)


def test_files_without_magic_or_carriers_header_are_read_with_a_warning():
    text = program(caston(range(2)), course(range(2)), header=[])
    with pytest.warns(KnitoutWarning) as said:
        graph = parse_knitout(text, "t.k")
    assert {str(w.message)[:12] for w in said} == {"no ';!knitou", "no ;;Carrier"}
    assert graph.chart().text() == ["KK"]


@pytest.mark.parametrize("op, said", [
    ("knot + f1 3", "unknown operation 'knot'"),
    ("knit + g1 3", "'g1' is not a needle"),
    ("knit * f1 3", "'*' is not a direction"),
    ("knit +- f1 3", "'+-' is not a direction"),
    ("knit + f+1 3", "'f+1' is not a needle"),
    ("knit +", "needs 3 parameters"),
    ("knit + f1 2", "carrier 2 is not in; bring it in"),
    ("knit + f1 9", "carrier 9 is not in the ;;Carriers header"),
    ("rack one", "'one' is not a number"),
    ("xfer f1 b2", "f1 and b2 do not face each other at racking 0"),
    ("xfer f1 f2", "not on opposite beds"),
    ("xfer f1", "needs 2 parameters"),
    ("drop f1 f2", "takes 1 parameters"),
    ("out 4", "carrier 4 is not in"),
    ("in 3", "carrier 3 is already in"),
    ("knit + fs1 3", "fs1 is a slider"),
])
def test_a_bad_line_is_one_error_naming_it(op, said):
    text = program(caston(range(3)), op)
    with pytest.raises(KnitError) as err:
        read(text)
    msg = str(err.value)
    assert msg.startswith("t.k:9: ") and said in msg and "\n" not in msg


def test_a_rack_of_a_quarter_aligns_no_needles_for_transfer():
    with pytest.raises(KnitError, match=r"t\.k:10: xfer f1 b1: .* racking 0.25"):
        read(program(caston(range(3)), "rack 0.25", "xfer f1 b1"))


def test_a_program_of_only_a_cast_on_has_no_chart():
    with pytest.raises(KnitError, match="no knitted course"):
        read(program(caston(range(3)))).chart()
