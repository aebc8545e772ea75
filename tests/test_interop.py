"""A cache is readable by other tools the guide names, as the guide shows it (docs/guide/caches.md):
pandas, Polars, Hugging Face ``datasets`` and DuckDB, each run from the guide's own snippet, without
importing phigenesis."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

#: The guide's page on caches, which holds the snippets (the README links to it).
README = (Path(__file__).resolve().parents[1] / "docs" / "guide" / "caches.md").read_text()


def readme_snippet(marker: str, cache: Path) -> str:
    """The guide's Python block between ``<!-- marker -->`` and ``<!-- /marker -->``, reading ``cache``."""
    found = re.search(rf"<!-- {marker} -->\n```python\n(.*?)```\n<!-- /{marker} -->", README, re.S)
    assert found, f"docs/guide/caches.md has no {marker} example"
    code = found.group(1)
    assert 'pathlib.Path("cache")' in code
    return code.replace('pathlib.Path("cache")', f"pathlib.Path({str(cache)!r})")


def run_python(code: str, tmp_path: Path, env: dict[str, str] | None = None) -> str:
    """Runs ``code`` in a fresh interpreter outside the checkout; checks it never imported phigenesis
    and returns its stdout."""
    code += "\nimport sys; assert not any(m.startswith('phigenesis') for m in sys.modules)"
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, **(env or {})},
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_hugging_face_datasets_reads_every_frame_of_a_cache_as_the_readme_shows(
    tiny_cache: Path, tmp_path: Path
) -> None:
    code = readme_snippet("hf-datasets", tiny_cache)
    code += (
        "\nrow = frames[4]"
        "\nassert frames.num_rows == 6 and 'boxes' in frames.column_names"
        "\nassert (row['scene_id'], row['frame_index']) == ('synthetic-s7-0001', 1)"
        "\nassert row['cameras'][0]['image'][:2] == b'\\xff\\xd8'  # the JPEG as stored"
        "\nassert len(row['cameras']) == 5 and len(row['boxes']) > 0"
    )
    hf_home = tmp_path / "hf"
    env = {"HF_DATASETS_OFFLINE": "1", "HF_HOME": str(hf_home)}
    env["HF_DATASETS_CACHE"] = str(hf_home / "datasets")
    out = run_python(code, tmp_path, env)
    assert out.split() == ["6", "synthetic-s7-0000", "5"]
    assert any((hf_home / "datasets").rglob("*.arrow"))  # its copy went to the cache it was given


def test_duckdb_queries_a_cache_through_pyarrow_as_the_readme_shows(tiny_cache: Path, tmp_path: Path) -> None:
    code = readme_snippet("duckdb", tiny_cache)
    code += (
        "\nrows = duckdb.sql('SELECT scene_id, frames, boxes_per_frame FROM per_scene ORDER BY scene_id')"
        ".fetchall()"
        "\nassert [(s, n) for s, n, _ in rows] == [('synthetic-s7-0000', 3), ('synthetic-s7-0001', 3)], rows"
        "\nassert all(b > 0 for _, _, b in rows)"
        '\ncars = duckdb.sql("SELECT count(*) FROM frames, unnest(boxes) AS t(b) "'
        "\"WHERE b.class_name = 'car'\")"
        "\nassert cars.fetchall()[0][0] > 0"
    )
    out = run_python(code, tmp_path)
    assert "synthetic-s7-0000" in out and "synthetic-s7-0001" in out


def test_pandas_reads_a_cache_as_the_readme_shows(tiny_cache: Path, tmp_path: Path) -> None:
    code = readme_snippet("pandas", tiny_cache)
    code += (
        "\nassert list(frames.columns) == ['scene_id', 'frame_index', 'frame_timestamp_micros']"
        "\nassert frames.groupby('scene_id').size().to_dict() == {'synthetic-s7-0000': 3}, frames"
        "\nassert len(boxes) > 0 and boxes['center_world'].map(len).eq(3).all()"
    )
    out = run_python(code, tmp_path)
    assert "synthetic-s7-0000" in out


def test_polars_scans_a_cache_as_the_readme_shows(tiny_cache: Path, tmp_path: Path) -> None:
    code = readme_snippet("polars", tiny_cache)
    code += (
        "\nassert per_scene['scene_id'].to_list() == ['synthetic-s7-0000', 'synthetic-s7-0001']"
        "\nassert per_scene['frames'].to_list() == [3, 3] and (per_scene['boxes_per_frame'] > 0).all()"
        "\ncars = frames.select(pl.col('boxes').explode().struct.field('class_name'))"
        "\nassert cars.filter(pl.col('class_name') == 'car').collect().height > 0"
    )
    out = run_python(code, tmp_path)
    assert "synthetic-s7-0000" in out and "synthetic-s7-0001" in out
