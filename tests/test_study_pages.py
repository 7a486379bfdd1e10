"""The study pages (analysis/study_pages.py): every number from the study's aggregated
CSV, a placeholder that matches no point refused, and the committed pages up to date."""

import csv
from pathlib import Path

import pytest

from analysis import study_pages as sp
from analysis.study_data import read_inputs

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

ROWS = [
    {"law": "paper", "agents.n": "1024", "estimator.delta": "0.1", "jobs": "2",
     "swarm_ratio_mean": "1.07", "swarm_ratio_ci_low": "0.5", "swarm_ratio_ci_high": "1.6",
     "phi_sup_mean": "0.11", "eps_sup_mean": "0.1"},
    {"law": "paper", "agents.n": "4096", "estimator.delta": "0.3", "jobs": "2",
     "swarm_ratio_mean": "2.0", "swarm_ratio_ci_low": "nan", "swarm_ratio_ci_high": "nan",
     "phi_sup_mean": "0.32", "eps_sup_mean": "0.3"},
    {"law": "heat", "agents.n": "1024", "estimator.delta": "0.0", "jobs": "2",
     "swarm_ratio_mean": "0.83", "swarm_ratio_ci_low": "0.7", "swarm_ratio_ci_high": "0.95",
     "phi_sup_mean": "0.001", "eps_sup_mean": "0.0"},
]  # fmt: skip

TEMPLATE = """---
table:
  where: {agents.n: 1024}
  sort: [law]
  columns:
    - law
    - {key: agents.n, label: N}
    - {stat: swarm_ratio, label: "`||swarm||` / floor", ci: true, fmt: .2f}
---
# A study

Paper at N = 1024: {{ci swarm_ratio @ law=paper,
agents.n=1024 : .2f}}; heat {{swarm_ratio @ law=heat}}; largest {{max swarm_ratio @
agents.n=1024|4096}}; gain {{gain phi_sup / eps_sup @ law=paper : .3f}}.

{{table}}

{{figure}}

{{commands}}
"""


def make_study(tmp_path: Path, template: str | None = TEMPLATE, name: str = "mine"):
    figures, docs = tmp_path / "figures", tmp_path / "docs"
    (figures / name).mkdir(parents=True)
    with (figures / name / "sweep_aggregated.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(ROWS[0]))
        writer.writeheader()
        writer.writerows(ROWS)
    (figures / name / "convergence.png").write_bytes(b"\x89PNG\r\n\x1a\nfake")
    (docs / "studies").mkdir(parents=True)
    if template is not None:
        (docs / "studies" / f"{name}.in.md").write_text(template)
    return sp.Study(name, figures, docs)


def test_a_page_takes_every_number_from_its_data(tmp_path):
    study = make_study(tmp_path)
    assert sp.main([study.name, "--figures", str(study.figures), "--docs", str(study.docs)]) == 0
    page = study.page.read_text()
    assert "Paper at N = 1024: 1.07 (0.50 to 1.60); heat 0.83; largest 2;" in page
    gain = (0.1 * 0.11 + 0.3 * 0.32) / (0.1**2 + 0.3**2)
    assert f"gain {gain:.3f}." in page
    table = [line for line in page.splitlines() if line.startswith("|")]
    assert table[0] == r"| law | N | `\|\|swarm\|\|` / floor |"
    assert table[2:] == ["| `heat` | `1024` | 0.83 (0.70 to 0.95) |",
                         "| `paper` | `1024` | 1.07 (0.50 to 1.60) |"]  # fmt: skip
    assert "![mine](../sweeps/mine.png)" in page
    assert "python -m analysis.study_pages mine" in page and "data/mine.csv" in page
    assert "{{" not in page
    assert study.data.read_text() == (study.figures / "mine" / "sweep_aggregated.csv").read_text()
    assert study.image.read_bytes().startswith(b"\x89PNG")


@pytest.mark.parametrize(
    "placeholder, why",
    [
        ("{{swarm_ratio @ law=paper}}", "2 points match"),
        ("{{swarm_ratio @ law=ot}}", "0 points match"),
        ("{{nosuch @ law=heat}}", "no column 'nosuch'"),
        ("{{swarm_ratio @ nokey=1}}", "no key 'nokey'"),
        ("{{gain phi_sup / eps_sup @ law=heat}}", "fewer than two points"),
        ("{{swarm_ratio @ law=heat", "unclosed placeholder"),
    ],
)
def test_a_placeholder_that_does_not_fit_the_data_stops_the_page(
    tmp_path, capsys, placeholder, why
):
    study = make_study(tmp_path, f"# A study\n\n{placeholder}\n")
    code = sp.main([study.name, "--figures", str(study.figures), "--docs", str(study.docs)])
    assert code == 2
    err = capsys.readouterr().err
    assert why in err and len(err.strip().splitlines()) == 1
    assert not study.page.exists()


def test_a_pivot_table_lays_a_statistic_out_by_two_keys(tmp_path):
    template = TEMPLATE.replace(
        "  where: {agents.n: 1024}\n  sort: [law]\n  columns:\n    - law\n"
        "    - {key: agents.n, label: N}\n"
        '    - {stat: swarm_ratio, label: "`||swarm||` / floor", ci: true, fmt: .2f}\n',
        "  pivot: {rows: law, columns: agents.n, stat: swarm_ratio, fmt: .2g}\n",
    )
    study = make_study(tmp_path, template)
    page = sp.render(study, read_inputs(study).rows)
    table = [line for line in page.splitlines() if line.startswith("|")]
    assert table[0] == r"| law \ agents.n | `1024` | `4096` |"
    assert table[2:] == ["| `heat` | 0.83 |  |", "| `paper` | 1.1 | 2 |"]


def test_a_study_without_a_template_gets_a_page_of_its_keys(tmp_path):
    study = make_study(tmp_path, template=None, name="smoke")
    page = sp.render(study, read_inputs(study).rows)
    assert "# Study `smoke`" in page and "swarm_ratio" in page and "{{" not in page


def test_a_page_without_data_renders_its_prose_and_says_where_the_numbers_come_from(tmp_path):
    docs = tmp_path / "docs"
    (docs / "studies").mkdir(parents=True)
    (docs / "studies" / "later.in.md").write_text("# Later\n\nQuoted.\n\n{{commands}}\n")
    study = sp.Study("later", tmp_path / "none", docs)
    page = sp.render(study)
    assert "No copy of the sweep's `sweep_aggregated.csv`" in page
    bad = docs / "studies" / "later.in.md"
    bad.write_text("# Later\n\n{{swarm_ratio @ law=paper}}\n")
    with pytest.raises(sp.PageError, match="no data"):
        sp.render(study)


@pytest.mark.parametrize("name", sp.studies(DOCS, ROOT / "no-figures"))
def test_the_committed_study_pages_are_rendered_from_their_templates_and_data(name):
    study = sp.Study(name, ROOT / "no-figures", DOCS)
    assert study.page.read_text() == sp.render(study), (
        f"docs/studies/{name}.md is not what its template and data give: "
        f"python -m analysis.study_pages {name}"
    )


GOOD_DATA = b"law,jobs,swarm_ratio_mean\r\npaper,2,1.07\r\n"


@pytest.mark.parametrize(
    "data, why",
    [
        (b"", "empty"),
        (b"law,agents.n,jobs,swarm_ratio_mean\r\npaper,1024,2,1.0", "cut short"),
        (b"law,agents.n,jobs,swarm_ratio_mean\r\npaper,1024\r\n", "cut short"),
        (b"law,agents.n,jo", "not an aggregated sweep CSV"),
        (b"name,price\r\nwidget,3\r\n", "not an aggregated sweep CSV"),
        (b"law,jobs,swarm_ratio_mean\r\n", "without rows"),
        (b"law,jobs,swarm_ratio_mean\r\npaper,2,\xff\xfe1.0\r\n", "not UTF-8"),
        (b'law,jobs,swarm_ratio_mean\r\n"paper,2,1.0\r\n', "cut short"),
    ],
    ids=["empty", "cut-mid-row", "short-row", "cut-header", "foreign", "header-only",
         "not-utf8", "open-quote"],
)  # fmt: skip
def test_a_bad_aggregated_csv_is_refused_in_one_line_before_anything_is_written(
    tmp_path, capsys, data, why
):
    study = make_study(tmp_path)
    study.data.parent.mkdir(parents=True)
    study.data.write_bytes(GOOD_DATA)
    study.page.write_text("the old page\n")
    (study.figures / study.name / "sweep_aggregated.csv").write_bytes(data)
    code = sp.main([study.name, "--figures", str(study.figures), "--docs", str(study.docs)])
    err = capsys.readouterr().err
    assert code == 2 and why in err and len(err.strip().splitlines()) == 1, err
    assert "sweep_aggregated.csv" in err
    assert study.data.read_bytes() == GOOD_DATA  # the committed data is kept
    assert study.page.read_text() == "the old page\n"
    assert not study.image.exists()  # nothing copied
    assert sorted(p.name for p in study.data.parent.iterdir()) == [f"{study.name}.csv"]


def test_a_fifo_or_a_non_png_in_place_of_an_input_is_refused_without_writing(tmp_path, capsys):
    import os

    study = make_study(tmp_path)
    source = study.figures / study.name / "sweep_aggregated.csv"
    source.unlink()
    os.mkfifo(source)  # would block an open() for reading
    args = [study.name, "--figures", str(study.figures), "--docs", str(study.docs)]
    assert sp.main(args) == 2
    assert "a FIFO" in capsys.readouterr().err
    assert not study.data.exists() and not study.page.exists()
    source.unlink()
    make_study(tmp_path / "again")  # a good CSV, beside a figure that is not a PNG
    study = sp.Study(study.name, tmp_path / "again" / "figures", tmp_path / "again" / "docs")
    (study.figures / study.name / "convergence.png").write_text("<html>")
    assert sp.main([*args[:1], "--figures", str(study.figures), "--docs", str(study.docs)]) == 2
    assert "not a PNG image" in capsys.readouterr().err
    assert not study.data.exists() and not study.page.exists()


def test_a_new_csv_is_written_only_when_its_page_renders(tmp_path, capsys):
    study = make_study(tmp_path, "# A study\n\n{{swarm_ratio @ law=nosuch}}\n")
    study.data.parent.mkdir(parents=True)
    study.data.write_bytes(GOOD_DATA)
    args = [study.name, "--figures", str(study.figures), "--docs", str(study.docs)]
    assert sp.main(args) == 2
    assert study.data.read_bytes() == GOOD_DATA and not study.page.exists()
