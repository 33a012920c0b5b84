"""Stitch patterns by name and by chart file (``knitfem.knit.chart``)."""

import numpy as np
import pytest

from knitfem.errors import KnitError
from knitfem.knit.chart import Chart, chart_from_spec, named_chart, read_chart


@pytest.mark.parametrize("name, bottom", [
    ("jersey", ["KKKKKK", "KKKKKK"]),
    ("rib1x1", ["KPKPKP", "KPKPKP"]),
    ("rib2x2", ["KKPPKK", "KKPPKK"]),
    ("garter", ["KKKKKK", "PPPPPP"]),
    ("seed", ["KPKPKP", "PKPKPK"]),
])
def test_named_patterns_start_at_the_bottom_left(name, bottom):
    chart = named_chart(name, 5, 6)
    assert chart.shape == (5, 6)
    assert chart.text() == (bottom * 3)[:5]
    assert chart.jersey == (name == "jersey")


def test_text_round_trips_and_equality():
    lines = ["KKPP", "PPKK", "KPKP"]
    chart = Chart.from_text(lines)
    assert chart.text() == lines
    assert chart == Chart(chart.purl)
    assert chart != Chart.from_text(lines[:2])
    assert chart != Chart.from_text(["KKPP", "PPKK", "KPKK"])
    assert str(chart).splitlines() == lines            # a chart file's lines
    assert not chart.purl.flags.writeable
    with pytest.raises(ValueError):
        Chart.from_text(["KPX"])
    with pytest.raises(ValueError):
        Chart.from_text(["KP", "K"])                  # ragged


def test_a_chart_file_skips_comments_and_blank_lines(tmp_path):
    path = tmp_path / "border.txt"
    path.write_text("# a 2x2 rib with a garter border\n\nKKKKKK\n  PPPPPP  \n"
                    "# the rib\nKKPPKK\n\n")
    chart = read_chart(str(path))
    assert chart.text() == ["KKKKKK", "PPPPPP", "KKPPKK"]
    assert chart_from_spec(str(path), 1, 1) == chart


@pytest.mark.parametrize("text, line, said", [
    ("KKPP\nKXPP\n", 2, "'X'"),
    ("# rib\nKPKP\n\nkpkp\n", 4, "'kp'"),
    ("KPKP\nKPK\n", 2, "3 stitches where the first had 4"),
    ("# only comments\n\n", None, "no course"),
])
def test_bad_chart_files_name_the_line(tmp_path, text, line, said):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(KnitError) as err:
        read_chart(str(path))
    msg = str(err.value)
    assert "\n" not in msg and said in msg
    assert msg.startswith(f"{path}:{line}:" if line else f"{path}:")


def test_specs_that_are_neither_a_name_nor_a_file():
    with pytest.raises(KnitError, match="neither a pattern"):
        chart_from_spec("ribbing", 4, 4)
    with pytest.raises(KnitError, match="at least one"):
        named_chart("seed", 0, 4)


def test_named_patterns_are_exact_grids():
    i, j = np.indices((7, 9))
    assert np.array_equal(named_chart("seed", 7, 9).purl, (i + j) % 2 == 1)
    assert np.array_equal(named_chart("rib2x2", 7, 9).purl, j % 4 >= 2)
