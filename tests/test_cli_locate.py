"""``instrument locate IMAGE... [--json]`` on image files written with cv2.imwrite."""

import json
import os
import resource
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from procedures.cli import main
from tests.synthetic_cross import render_cross


@pytest.fixture
def cross_8bit(tmp_path):
    img, truth = render_cross((240, 320), (171.3, 108.6), 0.12, 0.01, seed=21)
    path = tmp_path / "cross8.png"
    assert cv2.imwrite(str(path), img)
    return path, truth


@pytest.fixture
def cross_12bit(tmp_path):
    img, truth = render_cross((240, 320), (140.8, 131.1), -0.2, dtype=np.uint16, saturation=4095,
                              amplitude=6000.0, background=120.0, noise=30.0, seed=22)
    path = tmp_path / "cross12.png"
    assert cv2.imwrite(str(path), img)
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    return path, truth


def test_json_output_matches_truth(cross_8bit, cross_12bit, capsys):
    (p8, t8), (p12, t12) = cross_8bit, cross_12bit
    assert main(["locate", str(p8), "--json"]) == 0
    assert main(["locate", str(p12), "--json", "--saturation", "4095"]) == 0
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["image"] for r in records] == [str(p8), str(p12)]
    for record, truth in zip(records, (t8, t12)):
        assert "error" not in record
        assert np.hypot(*(np.array(record["center_px"]) - truth.center)) < 0.02
        assert record["angle_rad"] == pytest.approx(truth.angle, abs=2e-4)
        assert record["perpendicularity_rad"] == pytest.approx(truth.perpendicularity, abs=4e-4)
        for key in ("horizontal", "vertical"):
            line = record[key]
            assert line["sections"] > 150 and line["residual_rms_px"] < 0.05
            assert np.linalg.norm(line["direction"]) == pytest.approx(1.0)
    assert records[0]["horizontal"]["saturated_sections"] == 0
    assert records[1]["horizontal"]["saturated_sections"] > 150  # 6000 counts clip at 4095


def test_text_output_one_line_per_image(cross_8bit, capsys):
    path, truth = cross_8bit
    assert main(["locate", str(path), str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"{path}: centre ({truth.center[0]:.2f}")
    assert "angle" in lines[0] and "sections" in lines[0] and "saturated 0/0" in lines[0]


def test_errors_are_reported_per_image(cross_8bit, tmp_path, capsys):
    good, _ = cross_8bit
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((240, 320), 12, np.uint8))
    missing = tmp_path / "missing.png"
    assert main(["locate", str(blank), str(missing), str(good), "--json"]) == 1
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert "no cross" in records[0]["error"]
    assert records[1]["error"] == "cannot read image file"
    assert "error" not in records[2]
    # text mode: errors go to stderr, the good image still prints
    assert main(["locate", str(blank), str(good)]) == 1
    captured = capsys.readouterr()
    assert "no cross" in captured.err and str(good) in captured.out


def test_colour_file_is_read_as_grey(cross_8bit, tmp_path, capsys):
    path, truth = cross_8bit
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    colour = tmp_path / "colour.png"
    cv2.imwrite(str(colour), cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    assert main(["locate", str(colour), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert np.hypot(*(np.array(record["center_px"]) - truth.center)) < 0.02


# ------------------------------------------------------------------ decompression bombs, under a memory limit
BOMB_MEMORY_LIMIT = 1024 * 1024 * 1024  # address space of the child: far less than a 30000 × 30000 image needs
BOMB_TIMEOUT_S = 60  # what a hang is; the refusal itself must come well within BOMB_QUICK_S
BOMB_QUICK_S = 15


def _bomb_png(width: int, height: int) -> bytes:
    """A complete, valid 8-bit grey PNG of ``width`` × ``height`` zero pixels, of a few hundred KB.

    The zero rows are compressed once per block of rows; a full flush makes each block's deflate output
    independent of what came before, so the same bytes stand for every block and the file is built in
    milliseconds instead of pushing ``width × height`` bytes through zlib. The trailing Adler-32 of
    n zero bytes is (n mod 65521) << 16 | 1.
    """
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    rows_per_block = 1000
    assert height % rows_per_block == 0
    block = b"\x00" * ((width + 1) * rows_per_block)  # filter byte 0 + the row, per row
    compressor = zlib.compressobj(9)
    first = compressor.compress(block) + compressor.flush(zlib.Z_FULL_FLUSH)
    again = compressor.compress(block) + compressor.flush(zlib.Z_FULL_FLUSH)
    tail = compressor.flush(zlib.Z_FINISH)[:-4]  # the final (empty) block, without the checksum of two blocks
    total = (width + 1) * height
    stream = first + again * (height // rows_per_block - 1) + tail + struct.pack(">I", (total % 65521) << 16 | 1)
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", stream) + chunk(b"IEND", b"")


def _limited() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (BOMB_MEMORY_LIMIT, BOMB_MEMORY_LIMIT))


def _run_limited(argv: list[str]) -> tuple[int, str, float]:
    """``argv`` in a child under the memory limit and a timeout: (exit status, stderr, seconds)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    env.pop("OPENCV_IO_MAX_IMAGE_PIXELS", None)
    start = time.monotonic()
    done = subprocess.run(argv, capture_output=True, text=True, timeout=BOMB_TIMEOUT_S, preexec_fn=_limited, env=env)
    return done.returncode, done.stderr, time.monotonic() - start


def test_bomb_png_is_a_real_image():
    """The generator itself: a smaller one decodes to the zeros it declares."""
    data = _bomb_png(3000, 2000)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (2000, 3000) and image.dtype == np.uint8 and not image.any()
    assert len(_bomb_png(30000, 30000)) < 2_000_000


def _assert_refused(code: int, err: str, seconds: float, path: Path, width: int, height: int) -> None:
    from procedures.cli import MAX_IMAGE_PIXELS

    assert code == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{path}: image declares {width}×{height} pixels"), err
    assert str(MAX_IMAGE_PIXELS) in lines[0] and "Traceback" not in err
    assert seconds < BOMB_QUICK_S


def test_instrument_locate_refuses_a_png_bomb(tmp_path):
    path = tmp_path / "bomb.png"
    path.write_bytes(_bomb_png(30000, 30000))
    script = Path(sys.executable).with_name("instrument")
    argv = [str(script)] if script.exists() else [sys.executable, "-m", "procedures.cli"]
    _assert_refused(*_run_limited([*argv, "locate", str(path)]), path, 30000, 30000)


def _patched(ext: str, width: int, height: int) -> bytes:
    """A small image of type ``ext`` whose header is changed to declare ``width`` × ``height``."""
    data = bytearray(cv2.imencode(ext, np.zeros((16, 16), np.uint8))[1].tobytes())
    if ext == ".bmp":
        struct.pack_into("<ii", data, 18, width, height)
    elif ext == ".tiff":
        order = "<" if data[:2] == b"II" else ">"
        (offset,) = struct.unpack_from(order + "I", data, 4)
        (count,) = struct.unpack_from(order + "H", data, offset)
        for i in range(count):
            at = offset + 2 + 12 * i
            tag, kind = struct.unpack_from(order + "HH", data, at)
            if tag in (256, 257):
                struct.pack_into(order + "HHI", data, at, tag, 4, 1)
                struct.pack_into(order + "I", data, at + 8, width if tag == 256 else height)
    elif ext == ".pgm":
        data = bytearray(f"P5\n{width} {height}\n255\n".encode()) + data[data.index(b"255\n") + 4:]
    return bytes(data)


@pytest.mark.parametrize("ext", [".png", ".bmp", ".tiff", ".pgm"])
def test_bomb_is_refused_after_cv2_was_imported(tmp_path, ext):
    """OpenCV reads OPENCV_IO_MAX_IMAGE_PIXELS once, when it loads: in a process that imported cv2 first (a
    script calling ``main``, the suite) only the header check stands between a small file and gigabytes."""
    path = tmp_path / f"bomb{ext}"
    path.write_bytes(_bomb_png(30000, 30000) if ext == ".png" else _patched(ext, 30000, 30000))
    code = ("import sys, cv2\nfrom procedures.cli import main\nsys.exit(main(sys.argv[1:]))")
    _assert_refused(*_run_limited([sys.executable, "-c", code, "locate", str(path)]), path, 30000, 30000)


def test_declared_size_of_each_format():
    from procedures.cli import declared_image_size

    image = np.zeros((37, 53), np.uint8)
    for ext in (".png", ".bmp", ".tiff", ".jpg", ".pgm", ".pam"):
        assert declared_image_size(cv2.imencode(ext, image)[1].tobytes()) == (53, 37), ext
    assert declared_image_size(cv2.imencode(".tiff", image.astype(np.uint16))[1].tobytes()) == (53, 37)
    assert declared_image_size(b"GIF89a" + bytes(20)) is None and declared_image_size(b"") is None


def test_an_image_whose_size_cannot_be_read_is_refused(tmp_path, capsys):
    path = tmp_path / "odd.webp"
    ok, data = cv2.imencode(".webp", np.zeros((16, 16), np.uint8))
    assert ok
    path.write_bytes(data.tobytes())
    assert main(["locate", str(path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot read the image size from its header" in err[0]
