"""Fuzzing what an operator hands the CLI: procedure files, station files and image files.

Hypothesis generates near-valid and hostile inputs (broken YAML, raw bytes, other encodings, alias
bombs, deep nesting, huge integers, NaN and infinity, mutated stations, odd image formats, cut-off
files, an image header that claims 10^10 pixels) and runs ``instrument validate``, ``validate
STATION PROCEDURE`` (the offline dry run), ``run`` and ``locate`` on each, in a child process whose
address space is limited (``RLIMIT_AS``) and with an alarm on every call. Each call must end in
bounded time and memory with an exit status and one-line messages: no traceback, no "internal
error", no "out of memory". The child reports how many inputs of each kind it tried and how many
were accepted (the generators must reach both outcomes to mean anything).

``python -m tests.test_fuzz_inputs WORKDIR STATION EXAMPLES`` runs the child alone.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import resource
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
MEMORY_LIMIT = 1536 * 1024 * 1024  # the CLI's stack maps ~460 MB with one BLAS thread
CALL_SECONDS = 20  # no single call may take longer (the alarm turns a hang into a failure)
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def station(tmp_path_factory) -> Path:
    from sim_devices.cell import SimCell

    directory = tmp_path_factory.mktemp("fuzz")
    with SimCell(seed=4, directory=directory / "cell") as cell:
        text = cell.station_path.read_text(encoding="utf-8")
    path = directory / "station.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.timeout(600)
def test_no_input_gives_a_traceback_or_exhausts_the_machine(tmp_path, station):
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    child = subprocess.run([sys.executable, "-m", "tests.test_fuzz_inputs", str(tmp_path), str(station), "150"],
                           cwd=ROOT, capture_output=True, text=True, timeout=540, env=env)
    assert child.returncode == 0, child.stdout[-3000:] + child.stderr[-6000:]
    counts = json.loads(child.stdout.strip().splitlines()[-1])
    print(json.dumps(counts))
    for kind in ("procedure", "station", "image"):
        assert counts[kind]["tried"] == 150, counts
        assert 0 < counts[kind]["accepted"] < counts[kind]["tried"], counts  # both outcomes reached


# ------------------------------------------------------------------------------ the child process
def _png(width: int, height: int, payload: bytes) -> bytes:
    """A PNG whose header claims ``width`` × ``height`` grey pixels, whatever the payload holds."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(payload)) + chunk(b"IEND", b"")


def _call(argv: list[str]) -> tuple[int, str]:
    """``instrument ARGV`` in this process: (exit status, stderr); a hang becomes an exception."""
    from procedures.cli import main

    err = io.StringIO()
    signal.alarm(CALL_SECONDS)
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exc:  # argparse
                code = int(exc.code or 0)
    finally:
        signal.alarm(0)
    return code, err.getvalue()


def _judge(argv: list[str], allowed: tuple[int, ...] = (0, 1)) -> bool:
    code, err = _call(argv)
    bad = [marker for marker in ("Traceback", "internal error", "out of memory") if marker in err]
    assert code in allowed and not bad, f"instrument {' '.join(argv)} -> {code}: {err[-3000:]}"
    return code == 0


def _on_alarm(signum, frame):
    raise TimeoutError(f"a call took more than {CALL_SECONDS} s")


def child(workdir: Path, station: Path, examples: int) -> dict[str, dict[str, int]]:
    import numpy as np
    import yaml
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from procedures.kinds import KINDS
    from tests.synthetic_cross import render_cross

    signal.signal(signal.SIGALRM, _on_alarm)
    counts = {kind: {"tried": 0, "accepted": 0} for kind in ("procedure", "station", "image")}
    config = settings(derandomize=True, database=None, deadline=None, max_examples=examples,
                      suppress_health_check=list(HealthCheck))
    bad_station = workdir / "bad-station.yaml"
    bad_station.write_text("name: no devices\n", encoding="utf-8")
    runs = workdir / "runs"

    hostile_numbers = st.sampled_from([".nan", ".inf", "-.inf", "1e400", "-1e-400", "9" * 400, "9" * 4000,
                                       "0x" + "f" * 50, "-0", "1_000", "0o777", "2e-9"])
    scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**30, 10**30), st.floats(),
                        st.text(max_size=30), hostile_numbers.map(lambda text: yaml.safe_load(text)))
    values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=5)
                          | st.dictionaries(st.text(max_size=10), inner, max_size=5), max_leaves=12)
    keys = sorted({name for kind in KINDS.values() for name in kind.parameters.model_fields})
    plausible = st.one_of(st.integers(-5, 40), st.floats(-100, 100), st.booleans(),
                          st.lists(st.sampled_from(["x", "y", "z"]), min_size=1, max_size=3),
                          st.lists(st.floats(-1, 1), min_size=3, max_size=3),
                          st.lists(st.lists(st.floats(-1, 1), min_size=3, max_size=3), min_size=1, max_size=3),
                          hostile_numbers.map(lambda text: yaml.safe_load(text)))
    documents = st.one_of(
        st.fixed_dictionaries({"procedure": st.sampled_from(sorted(KINDS))},
                              optional={"parameters": st.dictionaries(st.sampled_from(keys), plausible, max_size=5),
                                        "name": st.text(max_size=20)}).map(lambda d: yaml.safe_dump(d)),
        st.fixed_dictionaries({}, optional={"procedure": st.sampled_from(sorted(KINDS)) | values,
                                            "parameters": values, "hooks": values}).map(lambda d: yaml.safe_dump(d)),
    )

    @st.composite
    def hostile_text(draw) -> bytes:
        kind = draw(st.sampled_from(["bomb", "deep", "digits", "special", "binary", "latin", "text", "anchors"]))
        head = "procedure: iso9283_repeatability\n"
        if kind == "bomb":
            width, levels = draw(st.integers(2, 12)), draw(st.integers(2, 12))
            lines = [head, "a0: &a0 [x" + ", x" * (width - 1) + "]\n"]
            lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]\n" for i in range(1, levels)]
            return "".join(lines).encode()
        if kind == "deep":
            depth = draw(st.integers(20, 6000))
            opening, closing = draw(st.sampled_from([("[", "]"), ("{a: ", "}")]))
            return (head + "parameters: " + opening * depth + "1" + closing * depth + "\n").encode()
        if kind == "digits":
            digits = "7" * draw(st.integers(300, 9000))
            return (head + f"parameters: {{{draw(st.sampled_from(keys))}: {digits}}}\n").encode()
        if kind == "special":
            return (f"procedure: {draw(st.sampled_from(sorted(KINDS)))}\nparameters: "
                    f"{{{draw(st.sampled_from(keys))}: {draw(hostile_numbers)}}}\n").encode()
        if kind == "binary":
            return draw(st.binary(max_size=400))
        if kind == "latin":
            return (head + "name: " + draw(st.text(max_size=20)) + "\n").encode("latin-1", errors="replace") + b"\xe9\n"
        if kind == "anchors":
            return (head + "parameters: &p {cycles: 3}\nname: *p\nhooks: [*p, *p]\n").encode()
        return draw(st.text(max_size=300)).encode()

    procedure_path = workdir / "procedure.yaml"

    @config
    @given(st.one_of(documents.map(str.encode), hostile_text()))
    def procedures(data: bytes) -> None:
        procedure_path.write_bytes(data)
        counts["procedure"]["tried"] += 1
        ok = _judge(["validate", str(procedure_path)])
        counts["procedure"]["accepted"] += ok
        _judge(["validate", str(station), str(procedure_path)])  # with the offline dry run
        _judge(["run", str(procedure_path), "--station", str(bad_station), "--runs-dir", str(runs)], (1,))

    base = yaml.safe_load(station.read_text(encoding="utf-8"))

    def paths(value: Any, prefix: tuple = ()) -> list[tuple]:
        found = [prefix] if prefix else []
        if isinstance(value, dict):
            for key, item in value.items():
                found += paths(item, prefix + (key,))
        elif isinstance(value, list):
            for index, item in enumerate(value):
                found += paths(item, prefix + (index,))
        return found

    every_path = paths(base)

    @st.composite
    def stations(draw) -> bytes:
        data = json.loads(json.dumps(base))
        for _ in range(draw(st.integers(0, 3))):
            where = draw(st.sampled_from(every_path))
            target = data
            try:
                for key in where[:-1]:
                    target = target[key]
                if draw(st.booleans()) and isinstance(target, dict):
                    target.pop(where[-1], None)
                else:
                    target[where[-1]] = draw(values)
            except (KeyError, IndexError, TypeError):
                continue  # an earlier change removed the path
        text = yaml.safe_dump(data, allow_unicode=True)
        if draw(st.integers(0, 9)) == 0:  # now and then, damage the text itself
            cut = draw(st.integers(0, len(text)))
            text = text[:cut] + draw(st.sampled_from(["\t", ": :", "&x *x", "\x00", "[", "\ufeff"])) + text[cut:]
        return text.encode("utf-8", errors="replace")

    station_path = workdir / "station.yaml"
    shipped = ROOT / "procedures" / "iso9283_repeatability.yaml"

    @config
    @given(stations())
    def station_files(data: bytes) -> None:
        station_path.write_bytes(data)
        counts["station"]["tried"] += 1
        counts["station"]["accepted"] += _judge(["validate", str(station_path)])
        _judge(["validate", str(station_path), str(shipped)])

    @st.composite
    def images(draw) -> bytes:
        import cv2

        kind = draw(st.sampled_from(["cross", "cross", "encoded", "encoded", "cut", "bytes", "claims"]))
        if kind == "cross":  # a cross the instrument should find (the suite's own synthetic images)
            image, _ = render_cross((draw(st.integers(120, 260)), draw(st.integers(160, 340))),
                                    center=(draw(st.floats(60, 100)), draw(st.floats(50, 70))),
                                    angle=draw(st.floats(-0.3, 0.3)), noise=draw(st.floats(0, 8)),
                                    seed=draw(st.integers(0, 1000)))
            return cv2.imencode(".png", image)[1].tobytes()
        if kind == "bytes":
            return draw(st.binary(max_size=2000))
        if kind == "claims":  # a header promising a huge image over a few bytes of data
            width, height = draw(st.integers(1, 100_000)), draw(st.integers(1, 100_000))
            return _png(width, height, b"\x00" * draw(st.integers(0, 64)))
        dtype = draw(st.sampled_from([np.uint8, np.uint16, np.float32]))
        shape = (draw(st.integers(1, 96)), draw(st.integers(1, 96))) + draw(st.sampled_from([(), (3,), (4,)]))
        rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
        array = (rng.random(shape) * (255 if dtype == np.uint8 else 4000)).astype(dtype)
        ext = draw(st.sampled_from([".png", ".bmp", ".tiff", ".pgm"] if dtype != np.float32 else [".tiff"]))
        if ext in (".bmp", ".pgm") and dtype == np.uint16:
            ext = ".png"
        if ext == ".pgm" and array.ndim == 3:
            ext = ".png"
        ok, encoded = cv2.imencode(ext, array)
        data = encoded.tobytes() if ok else b""
        if kind == "cut":
            data = data[: draw(st.integers(0, len(data)))]
        return data

    image_path = workdir / "image"

    @config
    @given(images())
    def image_files(data: bytes) -> None:
        image_path.write_bytes(data)
        counts["image"]["tried"] += 1
        counts["image"]["accepted"] += _judge(["locate", str(image_path), "--json"])

    procedures()
    station_files()
    image_files()
    return counts


if __name__ == "__main__":
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    result = child(Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]))
    print(json.dumps(result))
