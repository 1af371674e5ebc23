import numpy as np
import pytest

from recon.errors import LightFieldFormatError
from recon.lf.pfm import read_pfm, write_pfm


def test_round_trip_keeps_values_and_orientation(tmp_path):
    data = np.arange(12, dtype=np.float32).reshape(3, 4)
    data[0, 0] = np.nan
    write_pfm(tmp_path / "a.pfm", data)
    back = read_pfm(tmp_path / "a.pfm")
    np.testing.assert_array_equal(back, data)
    # On disk the rows are bottom-up: the first stored row is the last in memory.
    raw = (tmp_path / "a.pfm").read_bytes()
    first_row = np.frombuffer(raw[len(b"Pf\n4 3\n-1.0\n"):][:16], dtype="<f4")
    np.testing.assert_array_equal(first_row, data[2])


def test_reads_big_endian_and_colour(tmp_path):
    data = np.random.default_rng(0).random((2, 3, 3)).astype(np.float32)
    (tmp_path / "b.pfm").write_bytes(b"PF\n3 2\n1.0\n" + data[::-1].astype(">f4").tobytes())
    np.testing.assert_array_equal(read_pfm(tmp_path / "b.pfm"), data)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"P6\n2 2\n255\n" + bytes(12), "not a PFM file"),
        (b"Pf\nx 2\n-1.0\n" + bytes(16), "size or scale is not a number"),
        (b"Pf\n2 2\n-1.0\n" + bytes(8), "truncated"),
        (b"Pf\n", "header is incomplete"),
    ],
)
def test_broken_files_name_the_file_and_the_problem(tmp_path, content, message):
    path = tmp_path / "broken.pfm"
    path.write_bytes(content)
    with pytest.raises(LightFieldFormatError, match=message) as info:
        read_pfm(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(LightFieldFormatError, match="no such file"):
        read_pfm(tmp_path / "nope.pfm")
