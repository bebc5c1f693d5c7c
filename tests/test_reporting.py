"""Report helpers: stage timings from Snakemake benchmark files, RST tables to HTML."""
from stex.reporting import library_differences, stage_timings, tables_html


def _bench(path, seconds):
    path.write_text("s\th:m:s\tmax_rss\n" + f"{seconds}\t0:00:01\t10.0\n")


def test_stage_timings_sums_blocks(tmp_path):
    _bench(tmp_path / "tables_0000.tsv", 2.5)
    _bench(tmp_path / "tables_0001.tsv", 1.5)
    _bench(tmp_path / "labeling.tsv", 7.0)
    _bench(tmp_path / "ingest_block_0003.tsv", 1.0)
    t = stage_timings(tmp_path)
    assert t == {"tables": 4.0, "labeling": 7.0, "ingest_block": 1.0}
    assert stage_timings(tmp_path / "missing") == {}
    # a block left over from a run of the scene with more frames is not this run's
    assert stage_timings(tmp_path, n_blocks=2) == {"tables": 4.0, "labeling": 7.0}


def test_tables_html(tmp_path):
    rst = "Title\n-----\n\n+---+---+\n| a | b |\n+===+===+\n| 1 | 2 |\n+---+---+\n"
    html = tables_html(rst).decode()
    assert "<table" in html and "<td>1</td>" in html.replace("<td><p>1</p></td>", "<td>1</td>")


def test_library_differences_names_what_differs():
    same = {"python": "3.11.2", "numpy": "2.4.6", "scipy": "1.17.1"}
    assert library_differences({"a": same}) == ""
    assert library_differences({"a": same, "b": dict(same)}) == ""
    note = library_differences({"a": same, "b": {**same, "scipy": "1.16.3"}, "c": None})
    assert "scipy 1.17.1 (a), 1.16.3 (b)" in note and "not recorded for c" in note
    assert "numpy" not in note and "python" not in note
    note = library_differences({"a": same, "b": {k: v for k, v in same.items() if k != "scipy"}})
    assert "scipy 1.17.1 (a), not installed (b)" in note
