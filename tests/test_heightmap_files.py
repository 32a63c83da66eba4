"""Height map files (elo_mitsuba.heightmap): what write_height stores per format (NaN where no
height, the pixel size in TIFF resolution tags and the GSF header), read back by independent
readers, and `elo-mitsuba mesh` meshing those files without --pixel-size."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from elo_mitsuba.cli import main
from elo_mitsuba.errors import EloInputError
from elo_mitsuba.exr import read_exr
from elo_mitsuba.heightmap import read_heightmap, write_height

FIELD = (8.0, 6.0)  # mm: 16 x 12 px of 0.5 mm
SHAPE = (12, 16)
PIXEL = 0.5


def _height():
    rows, cols = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    return 0.01 * cols - 0.002 * rows  # mm, rises towards +x (columns) and +y (row 0)


def _mask():
    m = np.zeros(SHAPE, bool)
    m[2:4, 5:9] = True
    return m


META = {"quantity": "height map (relative, zero mean)", "units": "mm", "field_mm": list(FIELD), "method": "dct"}


def _read_gsf(path):
    """A reader written from the Gwyddion GSF specification alone: magic line, name = value lines,
    one to four NULs to a multiple of 4, little-endian float32 row by row."""
    raw = path.read_bytes()
    magic = b"Gwyddion Simple Field 1.0\n"
    assert raw.startswith(magic)
    end = raw.index(b"\0")
    header = dict(line.split(" = ", 1) for line in raw[len(magic):end].decode().splitlines())
    start = (end // 4 + 1) * 4  # the data start at the next multiple of 4 (1 to 4 NULs)
    assert raw[end:start] == b"\0" * (start - end)
    w, h = int(header["XRes"]), int(header["YRes"])
    data = struct.unpack(f"<{w * h}f", raw[start:])
    return header, np.asarray(data, dtype=np.float64).reshape(h, w)


def test_every_format_stores_nan_where_no_height_and_the_pixel_size(tmp_path):
    import tifffile

    h, m = _height(), _mask()
    for suffix in ("exr", "tif", "npy", "gsf"):
        write_height(tmp_path / f"h.{suffix}", h, m, META)
    # NPY: NaN at masked pixels, the heights elsewhere
    a = np.load(tmp_path / "h.npy")
    assert np.isnan(a[m]).all() and np.allclose(a[~m], h[~m])
    # TIFF: NaN, the JSON header, and the pixel size in the resolution tags (pixels per cm)
    with tifffile.TiffFile(tmp_path / "h.tif") as tif:
        page = tif.pages[0]
        t = page.asarray()
        assert page.tags["ResolutionUnit"].value == tifffile.RESUNIT.CENTIMETER
        num, den = page.tags["XResolution"].value
        assert num / den == pytest.approx(10.0 / PIXEL)
        num, den = page.tags["YResolution"].value
        assert num / den == pytest.approx(10.0 / PIXEL)
        assert json.loads(page.description)["field_mm"] == list(FIELD)
    assert np.isnan(t[m]).all() and np.allclose(t[~m], h[~m], atol=1e-7)
    # GSF: the documented header in metres, the data row 0 first, NaN at masked pixels
    header, g = _read_gsf(tmp_path / "h.gsf")
    assert (header["XRes"], header["YRes"]) == ("16", "12")
    assert float(header["XReal"]) == pytest.approx(FIELD[0] * 1e-3)
    assert float(header["YReal"]) == pytest.approx(FIELD[1] * 1e-3)
    assert header["XYUnits"] == "m" and header["ZUnits"] == "m"
    assert float(header["XOffset"]) == pytest.approx(-FIELD[0] / 2 * 1e-3)
    assert json.loads(header["ELOMitsuba"])["method"] == "dct"
    assert np.isnan(g[m]).all() and np.allclose(g[~m], h[~m] * 1e-3, rtol=1e-6, atol=1e-12)
    # EXR: 0 with the mask channel (the EXR writer refuses NaN), read back as NaN
    ch, meta = read_exr(tmp_path / "h.exr")
    assert (ch["height"][m] == 0).all() and (ch["mask"][m] == 1).all() and (ch["mask"][~m] == 0).all()
    assert "NaN" in meta["mask"]
    # each reads back with its pixel size (NPY records none)
    for suffix, pixel in (("exr", PIXEL), ("tif", PIXEL), ("gsf", PIXEL), ("npy", None)):
        r = read_heightmap(tmp_path / f"h.{suffix}", allow_nan=True)
        assert r.pixel_size_mm == (pytest.approx(pixel) if pixel else None), suffix
        assert np.isnan(r.height[m]).all() if suffix != "npy" else True
    with pytest.raises(EloInputError, match="trusted pixels"):
        write_height(tmp_path / "bad.npy", np.where(m, np.nan, h))  # NaN without a mask
    with pytest.raises(EloInputError, match="needs the pixel size"):
        write_height(tmp_path / "bare.gsf", h)


def test_foreign_tiff_resolution_tags_give_the_pixel_size(tmp_path):
    import tifffile

    h = _height()
    tifffile.imwrite(tmp_path / "inch.tif", h.astype(np.float32), resolution=(254.0, 254.0), resolutionunit="INCH")
    assert read_heightmap(tmp_path / "inch.tif").pixel_size_mm == pytest.approx(0.1)
    tifffile.imwrite(tmp_path / "none.tif", h.astype(np.float32))
    assert read_heightmap(tmp_path / "none.tif").pixel_size_mm is None


@pytest.mark.parametrize("suffix", ["exr", "tif", "gsf"])
def test_mesh_reads_the_pixel_size_of_a_height_output(tmp_path, capsys, suffix):
    write_height(tmp_path / f"h.{suffix}", _height(), None, META)
    assert main(["mesh", str(tmp_path / f"h.{suffix}"), "-o", str(tmp_path / "m.ply")]) == 0
    out = capsys.readouterr().out
    assert "pixel 0.5 mm" in out and "x [-3.75, 3.75] y [-2.75, 2.75]" in out
    # the same pixel size given again is fine; another is refused in one line
    assert main(["mesh", str(tmp_path / f"h.{suffix}"), "-o", str(tmp_path / "m.ply"), "--overwrite",
                 "--pixel-size", "0.5"]) == 0
    capsys.readouterr()
    assert main(["mesh", str(tmp_path / f"h.{suffix}"), "-o", str(tmp_path / "n.ply"), "--pixel-size", "0.4"]) == 2
    err = capsys.readouterr().err
    assert "--pixel-size 0.4 mm contradicts" in err and err.count("\n") == 1
    assert main(["mesh", str(tmp_path / f"h.{suffix}"), "-o", str(tmp_path / "n.ply"), "--units", "um"]) == 2
    assert "records its heights in" in capsys.readouterr().err


def test_mesh_refuses_what_it_cannot_know(tmp_path, capsys):
    np.save(tmp_path / "h.npy", _height())
    assert main(["mesh", str(tmp_path / "h.npy"), "-o", str(tmp_path / "m.ply")]) == 2
    assert "records no pixel size; give --pixel-size" in capsys.readouterr().err
    write_height(tmp_path / "masked.exr", _height(), _mask(), META)  # no height at 8 pixels
    assert main(["mesh", str(tmp_path / "masked.exr"), "-o", str(tmp_path / "m.ply")]) == 2
    assert "8 non-finite height(s)" in capsys.readouterr().err


def test_an_xyz_point_list_csv_is_not_meshed_as_a_grid(tmp_path, capsys):
    """A profilometer's x, y, z export (3 columns, one row per point) is refused in one line; grids
    of 3 columns and fewer than 16 rows, and of 16 rows and other widths, are still heights."""
    y, x = np.mgrid[0:4, 0:4]
    points = np.stack([x.ravel(), y.ravel(), 0.01 * x.ravel()], axis=-1)  # 16 points of a 4 x 4 grid
    np.savetxt(tmp_path / "xyz.csv", points, delimiter=",")
    out = tmp_path / "m.ply"
    assert main(["mesh", str(tmp_path / "xyz.csv"), "-o", str(out), "--pixel-size", "0.2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "3 columns and 16 rows" in err and "x, y, z point list" in err, err
    assert "rows = y, columns = x" in err and not out.exists()
    np.savetxt(tmp_path / "narrow.csv", points[:15], delimiter=",")
    assert read_heightmap(tmp_path / "narrow.csv").height.shape == (15, 3)
    np.savetxt(tmp_path / "tall.csv", np.zeros((16, 4)), delimiter=",")
    assert read_heightmap(tmp_path / "tall.csv").height.shape == (16, 4)
