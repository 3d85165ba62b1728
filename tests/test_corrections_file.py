"""Corrections files (JSON Lines): every kind of error located at its line, the version key,
unknown keys, and a write/read round trip that keeps every number exactly."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hitl_slam.corrections import Correction, Mode
from hitl_slam.corrections_file import (
    Apply,
    Redo,
    Step,
    Undo,
    read_corrections,
    write_corrections,
)
from hitl_slam.errors import InputError
from hitl_slam.io.textfile import MAX_COORDINATE

A = [[1.2, 3.4], [4.1, 3.45]]
B = [[10.0, 3.9], [13.2, 4.0]]
GOOD = json.dumps({"mode": "collinear", "a": A, "b": B})


def write(tmp_path: Path, *lines: str, name: str = "c.jsonl") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def error_of(path: Path) -> str:
    with pytest.raises(InputError) as info:
        read_corrections(path)
    return str(info.value)


def test_reads_corrections_undo_redo_with_line_numbers(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        GOOD,
        "",
        "   ",
        json.dumps({"mode": "colocation", "a": A, "b": B, "sigma_h": 0.08}),
        '{"action": "undo"}',
        '{"action": "redo", "version": 1}',
    )
    steps = read_corrections(path)
    assert [type(s) for s in steps] == [Apply, Apply, Undo, Redo]
    assert [s.line for s in steps] == [1, 4, 5, 6]
    first, second = steps[0], steps[1]
    assert isinstance(first, Apply)
    assert isinstance(second, Apply)
    assert first.drawn == Correction.make(A, B, Mode.COLLINEAR)
    assert first.drawn.sigma_h is None
    assert second.drawn.mode is Mode.COLOCATION
    assert second.drawn.sigma_h == 0.08


def test_version_key_and_header_line(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        '{"version": 1}',
        json.dumps({"version": 1, "mode": "parallel", "a": A, "b": B}),
    )
    steps = read_corrections(path)
    assert len(steps) == 1
    assert steps[0].line == 2


def test_empty_file_and_bom(tmp_path: Path) -> None:
    assert read_corrections(write(tmp_path, "")) == []
    path = tmp_path / "bom.jsonl"
    path.write_bytes(b"\xef\xbb\xbf" + GOOD.encode() + b"\r\n")
    assert len(read_corrections(path)) == 1


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("{not json", "not valid JSON"),
        ('{"mode": "collinear", "a": ' + json.dumps(A) + "}", "missing 'b'"),
        ('{"mode": "collinear"}', "missing 'a', 'b'"),
        ("[1, 2]", "expected a JSON object, got list"),
        ("null", "expected a JSON object, got null"),
        ("{}", "empty object"),
        ("# a comment", "no comments"),
        (json.dumps({"mode": "diagonal", "a": A, "b": B}), 'unknown mode "diagonal"'),
        (json.dumps({"mode": 3, "a": A, "b": B}), "unknown mode 3"),
        (
            json.dumps({"mode": "collinear", "a": A, "b": B, "sigmah": 0.1}),
            "did you mean 'sigma_h'",
        ),
        (json.dumps({"mode": "collinear", "a": A, "b": B, "colour": 1}), "unknown key 'colour'"),
        (json.dumps({"mode": "collinear", "a": [[1, 2]], "b": B}), "'a' must be two [x, y]"),
        (json.dumps({"mode": "collinear", "a": A, "b": [[1, 2], [3]]}), "'b' must be two"),
        (json.dumps({"mode": "collinear", "a": [["1", 2], [3, 4]], "b": B}), "'a' must be"),
        (json.dumps({"mode": "collinear", "a": [[True, 2], [3, 4]], "b": B}), "'a' must be"),
        ('{"mode": "collinear", "a": [[1e999, 2], [3, 4]], "b": ' + json.dumps(B) + "}", "large"),
        ('{"mode": "collinear", "a": [[NaN, 2], [3, 4]], "b": ' + json.dumps(B) + "}", "NaN"),
        (json.dumps({"mode": "collinear", "a": A, "b": B, "sigma_h": -1}), "sigma_h must be"),
        (json.dumps({"mode": "collinear", "a": A, "b": B, "sigma_h": "0.1"}), "sigma_h must be"),
        (json.dumps({"mode": "collinear", "a": A, "b": B, "sigma_h": 0}), "sigma_h must be"),
        ('{"mode": "collinear", "mode": "parallel", "a": [], "b": []}', "appears twice"),
        ('{"action": "undo", "version": 2}', "unsupported version 2"),
        ('{"action": "undo", "version": true}', "unsupported version true"),
        ('{"action": "undo", "version": "1"}', 'unsupported version "1"'),
        ('{"action": "rewind"}', 'unknown action "rewind"'),
        ('{"action": "undo", "count": 2}', "unknown key 'count'"),
        ('{"action": "undo", "mode": "collinear"}', "both 'action' and 'mode'"),
    ],
)
def test_every_error_names_file_and_line(tmp_path: Path, line: str, message: str) -> None:
    path = write(tmp_path, GOOD, "", line, GOOD)
    text = error_of(path)
    assert text.startswith(f"{path}:3: "), text
    assert message in text, text
    assert "; " in text  # what is wrong; what to do
    assert "\n" not in text


def test_line_numbers_follow_the_editor_not_unicode_line_breaks(tmp_path: Path) -> None:
    # U+2028 inside a JSON string is legal and must not count as a line break.
    weird = json.dumps({"mode": "collinear", "a": A, "b": B, "note\u2028": 1}, ensure_ascii=False)
    path = write(tmp_path, GOOD, weird)
    assert f"{path}:2: unknown key" in error_of(path)


def test_not_utf8_missing_and_directory(tmp_path: Path) -> None:
    path = tmp_path / "latin1.jsonl"
    path.write_bytes(GOOD.encode() + b"\n\xe9\n")
    assert f"{path}:2: not UTF-8" in error_of(path)
    missing = tmp_path / "missing.jsonl"
    assert "no such file" in error_of(missing)
    assert str(tmp_path) in error_of(tmp_path)


def test_write_read_round_trip_and_atomic_replace(tmp_path: Path) -> None:
    steps: list[Step] = [
        Apply(Correction.make(A, B, "collinear")),
        Apply(Correction.make([[0.1, 0.2], [0.3, 1e-300]], B, "perpendicular", 0.07)),
        Undo(),
        Redo(),
    ]
    path = tmp_path / "out.jsonl"
    path.write_text("old content that must be replaced whole\n")
    write_corrections(path, steps)
    back = read_corrections(path)
    assert [type(s) for s in back] == [Apply, Apply, Undo, Redo]
    assert [s.line for s in back] == [1, 2, 3, 4]
    for original, read in zip(steps[:2], back[:2], strict=True):
        assert isinstance(original, Apply)
        assert isinstance(read, Apply)
        assert read.drawn == original.drawn
    lines = path.read_text().splitlines()
    assert json.loads(lines[2]) == {"action": "undo"}
    assert [p.name for p in tmp_path.iterdir()] == ["out.jsonl"]  # no temporary left behind


def test_write_accepts_bare_drawn_corrections(tmp_path: Path) -> None:
    drawn = Correction.make(A, B, "parallel")
    path = tmp_path / "c.jsonl"
    write_corrections(path, [drawn, drawn])
    assert [s.drawn for s in read_corrections(path) if isinstance(s, Apply)] == [drawn, drawn]


def test_write_to_missing_directory_is_an_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot write"):
        write_corrections(tmp_path / "no" / "c.jsonl", [Undo()])


def test_write_refuses_what_would_not_read_back(tmp_path: Path) -> None:
    far = Correction.make([[0.0, 0.0], [2e9, 0.0]], B, "collinear")
    path = tmp_path / "c.jsonl"
    with pytest.raises(InputError, match=r"step 2 .*1e9") as info:
        write_corrections(path, [Undo(), Apply(far)])
    assert str(info.value).startswith(f"{path}: ")
    assert not path.exists()


coordinate = st.floats(min_value=-MAX_COORDINATE, max_value=MAX_COORDINATE, width=64)
segment = st.tuples(st.tuples(coordinate, coordinate), st.tuples(coordinate, coordinate))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.builds(
                Correction.make,
                segment,
                segment,
                st.sampled_from(list(Mode)),
                st.one_of(st.none(), st.floats(min_value=1e-6, max_value=10.0)),
            ),
            st.just("undo"),
            st.just("redo"),
        ),
        max_size=8,
    )
)
def test_round_trip_is_exact(items: list[Correction | str]) -> None:
    import tempfile

    steps: list[Step] = [
        Undo() if i == "undo" else Redo() if i == "redo" else Apply(i)  # type: ignore[arg-type]
        for i in items
    ]
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "c.jsonl"
        write_corrections(path, steps)
        back = read_corrections(path)
    assert len(back) == len(steps)
    for original, read in zip(steps, back, strict=True):
        assert type(original) is type(read)
        if isinstance(original, Apply):
            assert isinstance(read, Apply)
            assert read.drawn == original.drawn
