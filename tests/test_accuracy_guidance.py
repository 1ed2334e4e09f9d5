"""Every number that the guidance of docs/accuracy-vs-time.md ("Which settings should I
use", and the sentences of "More choices") quotes is a figure of the data: a cell of a
table on that page, or a value of the study's JSON (benchmarks/results/accuracy_*.json
and the quantization_bias.json the guidance cites), at the precision the sentence prints
it. So when the study is regenerated and a figure changes, the sentence that quotes it
fails here instead of going stale. Units that are not data (1/255 bounds, 8-bit steps)
are stripped first; NON_DATA lists the few constants the text quotes that no row holds.
"""

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "accuracy-vs-time.md"
RESULTS = ROOT / "benchmarks" / "results"
DATA_FILES = sorted(RESULTS.glob("accuracy_*.json")) + [RESULTS / "quantization_bias.json"]
NON_DATA = {"0.999"}  # Adam's beta2, a constant of the optimizer
# a number as the page prints one: 5,120  0.75  4.4e-3  1e-4, then an optional percent sign
NUMBER = re.compile(r"(?<![\w.])(\d{1,3}(?:,\d{3})+|\d+(?:\.\d+)?(?:e[-+]?\d+)?)(?![\w.]*\d)"
                    r"(\s*%)?")


#: the sections whose prose gives advice: (heading, where its prose ends)
PROSE = (("## Which settings should I use", "\n## "),
         ("## More choices", "\n### Tables of the choices"))


def guidance(page, heading=PROSE[0][0], end=PROSE[0][1]):
    """The text of a guidance section, without code spans, link targets and the /255 of
    bounds written in 1/255 units."""
    text = page.split(heading, 1)[1].split(end, 1)[0]
    text = re.sub(r"`[^`]*`", " ", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)
    return re.sub(r"/255", " ", text)


def quoted(text):
    """[(token, value)] of the numbers in text; a percentage's value is its fraction."""
    out = []
    for token, percent in NUMBER.findall(text):
        value = float(token.replace(",", ""))
        out.append((token + ("%" if percent else ""), value / 100 if percent else value))
    return out


def table_values(page):
    """The numbers in the cells of the page's markdown tables and text tables."""
    cells = [line for line in page.splitlines() if line.startswith("|")
             or re.match(r"^\s*\w+\s+\d", line)]
    return [v for line in cells for _, v in quoted(line.replace("|", " "))]


def json_values(node):
    """Every number (not a bool) of a JSON document, the machine record left out."""
    if isinstance(node, dict):
        return [v for k, item in node.items() if k != "machine" for v in json_values(item)]
    if isinstance(node, list):
        return [v for item in node for v in json_values(item)]
    return [float(node)] if isinstance(node, int | float) and not isinstance(node, bool) else []


def printed_as(value, token):
    """Whether value prints as token at token's precision (decimals or significant
    digits); a percentage compares its fraction at the printed percent's decimals."""
    digits = token.rstrip("%")
    scale = 100.0 if token.endswith("%") else 1.0
    if "e" in digits:
        mantissa = digits.split("e")[0]
        places = len(mantissa.split(".")[1]) if "." in mantissa else 0
        return float(f"{value:.{places}e}") == float(digits)
    places = len(digits.split(".")[1]) if "." in digits else 0
    return round(value * scale, places) == round(float(digits.replace(",", "")), places)


def unsupported(text, values):
    """The tokens of text that no value prints as."""
    return [token for token, _ in quoted(text)
            if token not in NON_DATA and not any(printed_as(v, token) for v in values)]


def data_values(page):
    values = table_values(page)
    for path in DATA_FILES:
        values += json_values(json.loads(path.read_text()))
    return values


@pytest.mark.parametrize("heading, end", PROSE)
def test_every_number_in_the_guidance_is_a_figure_of_the_data(heading, end):
    page = PAGE.read_text()
    text = guidance(page, heading, end)
    assert len(quoted(text)) > 50, f"{heading}: not found, or it lost its figures"
    assert unsupported(text, data_values(page)) == []


def test_a_figure_the_data_does_not_have_is_reported():
    page = PAGE.read_text()
    values = data_values(page)
    # 0.43/255 is a row of the supersampling table; 0.4321 and 7.77e-5 are not data
    text = "128 px with 4x supersampling (0.43/255); 0.4321/255; an error of 7.77e-5; 55.57 %"
    assert unsupported(guidance("## Which settings should I use\n" + text), values) == [
        "0.4321", "7.77e-5", "55.57%"]


def test_numbers_are_read_as_printed():
    assert quoted("5,120 faces, 4.4e-3, 1e-4 and 0.7–1.9 % at 128²") == [
        ("5,120", 5120.0), ("4.4e-3", 4.4e-3), ("1e-4", 1e-4), ("0.7", 0.7), ("1.9%", 0.019),
        ("128", 128.0)]
    assert printed_as(0.0044127, "4.4e-3") and not printed_as(0.0045, "4.4e-3")
    assert printed_as(0.0070539, "0.7%") and printed_as(1280, "1,280")
