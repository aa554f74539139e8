"""Radiograph stacks to profiles: synthetic TIFF stacks made from a known profile.

The stacks mimic an sCMOS measurement: a dark offset of ~100 counts with a fixed
pattern and read noise, an open beam of ~2000 counts with a smooth flat-field shape
and Poisson noise, the sample transmission (a smoothed box with refraction peaks,
0.70..1.15, along the columns, optionally tilted) and saturated gamma spots in a few
frames.
"""

import argparse
import math

import numpy as np
import pytest
import tifffile

from fwdfit import FwdfitError
from fwdfit.cli import build_parser
from fwdfit.images import (
    Roi,
    clipped_mean_frames,
    combine_frames,
    edge_angle_deg,
    frame_layout,
    iter_frame_rows,
    profile_from_stacks,
    remove_spots,
    sheared_roi,
    tiff_files,
    write_profile_csv,
)

N_ROWS, N_COLS = 64, 200
ROI = (4, 60, 10, 190)
PIXEL_UM = 2.4
OPEN_COUNTS = 2000.0
DARK_COUNTS = 100.0
N_SAMPLE, N_OPEN, N_DARK = 10, 6, 4
SATURATED = 65535


def true_profile(u):
    """Transmission at ROI column coordinate ``u`` (pixels): box 50..130 with edge peaks."""
    def step(x):
        return 0.5 * (1 + np.tanh(x / 2.5))

    def bump(x, width):
        return np.exp(-0.5 * (x / width) ** 2)

    box = step(u - 50) - step(u - 130)
    peaks = bump(u - 45, 3.5) + bump(u - 135, 3.5)
    dips = bump(u - 55, 3.5) + bump(u - 125, 3.5)
    return 1.0 - 0.22 * box + 0.15 * peaks - 0.04 * dips


def transmission_image(tilt_deg):
    """``(N_ROWS, N_COLS)`` true T, edges tilted by ``tilt_deg`` about the ROI centre."""
    angle = math.radians(tilt_deg)
    centre_row = (ROI[0] + ROI[1] - 1) / 2
    centre_col = (ROI[2] + ROI[3] - 1) / 2
    rows, cols = np.mgrid[0:N_ROWS, 0:N_COLS].astype(float)
    across = (centre_col + (cols - centre_col) * math.cos(angle)
              - (rows - centre_row) * math.sin(angle))
    return true_profile(across - ROI[2])


def add_spots(frame, rng):
    """Saturate 12 single pixels, a 2x2 cluster and a 3-pixel vertical streak."""
    rows = rng.integers(0, N_ROWS, 12)
    cols = rng.integers(0, N_COLS, 12)
    frame[rows, cols] = SATURATED
    r, c = rng.integers(5, N_ROWS - 5), rng.integers(5, N_COLS - 5)
    frame[r:r + 2, c:c + 2] = SATURATED
    r, c = rng.integers(5, N_ROWS - 5), rng.integers(5, N_COLS - 5)
    frame[r:r + 3, c] = SATURATED


def make_stacks(root, *, tilt_deg=0.0, dose=1.0, spots=True, seed=0):
    """Write sample (folder of single pages), open (one multi-page zlib file) and dark
    (glob of float32 files) stacks under ``root``; return their specs."""
    rng = np.random.default_rng(seed)
    spot_rng = np.random.default_rng(seed + 1000)
    rows, cols = np.mgrid[0:N_ROWS, 0:N_COLS]
    flat = 1 + 0.08 * np.sin(rows / 20.0) + 0.1 * np.cos(cols / 50.0)
    dark_pattern = DARK_COUNTS + 5 * rng.standard_normal((N_ROWS, N_COLS))
    T = transmission_image(tilt_deg)

    def frame(counts, with_spots):
        data = dark_pattern + rng.poisson(counts) + 2 * rng.standard_normal(counts.shape)
        data = np.clip(np.round(data), 0, SATURATED).astype(np.uint16)
        if with_spots:
            add_spots(data, spot_rng)
        return data

    (root / "sample").mkdir()
    for i in range(N_SAMPLE):
        data = frame(OPEN_COUNTS * dose * flat * T, spots and i in (1, 4, 7))
        tifffile.imwrite(root / "sample" / f"frame_{i:03d}.tif", data)
    open_frames = np.stack([frame(OPEN_COUNTS * flat, spots and i == 2) for i in range(N_OPEN)])
    tifffile.imwrite(root / "open.tif", open_frames, photometric="minisblack",
                     compression="zlib")
    for i in range(N_DARK):
        data = frame(np.zeros((N_ROWS, N_COLS)), spots and i == 1)
        tifffile.imwrite(root / f"dark_{i}.tiff", data.astype(np.float32))
    return {"sample": root / "sample", "open_beam": root / "open.tif",
            "dark": str(root / "dark_*.tiff")}


def truth(tilt_deg=0.0):
    """True T at the profile's x: ROI column j of the straightened ROI lies
    ``j cos(tilt)`` from column 0 across the edges, which the shear about the ROI's centre
    moves by ``(centre - C0) (1 - cos(tilt))``."""
    cos = math.cos(math.radians(tilt_deg))
    j = np.arange(ROI[3] - ROI[2], dtype=float)
    return true_profile(j * cos + ((ROI[2] + ROI[3] - 1) / 2 - ROI[2]) * (1 - cos))


def assert_matches_truth(profile, expected):
    pull = (profile.T - expected) / profile.T_err
    assert np.mean(np.abs(pull) < 4) >= 0.99
    rms = math.sqrt(np.mean(pull**2))
    assert 0.7 < rms < 1.3, rms


@pytest.fixture(scope="module")
def stacks(tmp_path_factory):
    return make_stacks(tmp_path_factory.mktemp("stacks"))


@pytest.fixture(scope="module")
def clean_stacks(tmp_path_factory):
    return make_stacks(tmp_path_factory.mktemp("clean"), spots=False)


# ----------------------------------------------------------------------------- reading


def test_tiff_files_expands_file_folder_and_glob(tmp_path):
    for name in ("b.tif", "a.TIFF", "c.tif"):
        tifffile.imwrite(tmp_path / name, np.zeros((2, 3), np.uint16))
    (tmp_path / "notes.txt").write_text("not a frame")
    assert [p.name for p in tiff_files(tmp_path)] == ["a.TIFF", "b.tif", "c.tif"]
    assert [p.name for p in tiff_files(str(tmp_path / "*.tif"))] == ["b.tif", "c.tif"]
    assert tiff_files(tmp_path / "c.tif") == [tmp_path / "c.tif"]


@pytest.mark.parametrize("spec, message", [
    ("empty", "no TIFF files"), ("nothing_*.tif", "no files match"), ("missing.tif", "no such"),
])
def test_tiff_files_rejects_empty_and_missing(tmp_path, spec, message):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FwdfitError, match=message) as error:
        tiff_files(str(tmp_path / spec))
    assert str(tmp_path / spec) in str(error.value)


@pytest.mark.parametrize("options", [
    {}, {"compression": "zlib"}, {"byteorder": ">"}, {"tile": (16, 16)},
])
@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_iter_frame_rows_reads_pages_and_row_ranges(tmp_path, options, dtype):
    data = np.arange(3 * 32 * 48).reshape(3, 32, 48).astype(dtype)
    tifffile.imwrite(tmp_path / "multi.tif", data, photometric="minisblack", **options)
    tifffile.imwrite(tmp_path / "single.tif", data[0] + 1)
    files = [tmp_path / "multi.tif", tmp_path / "single.tif"]
    assert frame_layout(files) == (4, (32, 48))
    blocks = list(iter_frame_rows(files, 5, 19))
    expected = np.concatenate([data, data[:1] + 1])[:, 5:19]
    np.testing.assert_array_equal(np.stack(blocks), expected)
    assert all(block.dtype == np.float32 for block in blocks)


def test_frames_of_different_shapes_are_rejected(tmp_path):
    tifffile.imwrite(tmp_path / "a.tif", np.zeros((8, 10), np.uint16))
    tifffile.imwrite(tmp_path / "b.tif", np.zeros((8, 11), np.uint16))
    with pytest.raises(FwdfitError, match="differ in shape") as error:
        frame_layout(tiff_files(tmp_path))
    assert "b.tif" in str(error.value) and "8x11" in str(error.value)


def test_unreadable_file_is_named(tmp_path):
    (tmp_path / "broken.tif").write_bytes(b"this is not a TIFF file at all")
    with pytest.raises(FwdfitError, match="cannot read TIFF file .*broken.tif"):
        frame_layout([tmp_path / "broken.tif"])


@pytest.mark.parametrize("compression", [None, "zlib"])
def test_truncated_file_is_named(tmp_path, compression):
    path = tmp_path / "truncated.tif"
    tifffile.imwrite(path, np.arange(6400, dtype=np.uint16).reshape(64, 100),
                     compression=compression)
    path.write_bytes(path.read_bytes()[:-3000])
    with pytest.raises(FwdfitError, match="cannot read page 0 of .*truncated.tif"):
        list(iter_frame_rows([path], 0, 64))


def test_colour_frames_are_rejected(tmp_path):
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((8, 10, 3), np.uint8), photometric="rgb")
    with pytest.raises(FwdfitError, match="not a single-channel image"):
        frame_layout([tmp_path / "rgb.tif"])


# ----------------------------------------------------------------- spots and combining


def test_remove_spots_removes_spots_and_keeps_lines_along_columns():
    h = 3  # rows of context above and below
    rng = np.random.default_rng(1)
    frame = 2000 + 45 * rng.standard_normal((40 + 2 * h, 80))
    frame[:, 30] += 400  # a one-pixel refraction peak along the column, ~9 sigma: kept
    frame[:, 50:52] -= 600  # a dark two-pixel line
    spotted = frame.copy()
    spots = [(10, 10), (20, 30), (25, 60), (25, 61), (26, 60), (26, 61),
             (30, 70), (31, 70), (32, 70)]  # a single pixel, one on the line, 2x2, 3x1
    for r, c in spots:
        spotted[r, c] = SATURATED
    cleaned = remove_spots(spotted, 5.0)
    centre = frame[h:-h]
    assert cleaned.shape == centre.shape
    assert cleaned.max() < 3000
    assert abs(cleaned[20 - h, 30] - 2400) < 150  # the spot on the line took the line's level
    on_line = np.arange(40) != 20 - h
    np.testing.assert_array_equal(cleaned[on_line, 30], centre[on_line, 30])
    changed = np.count_nonzero(cleaned != centre)
    assert len(spots) <= changed <= len(spots) + 2  # at most two noise pixels replaced


def test_remove_spots_does_not_bias_low_quantised_counts():
    rng = np.random.default_rng(2)
    frame = rng.poisson(3.0, (206, 200)).astype(np.float32)
    cleaned = remove_spots(frame, 5.0)
    assert abs(cleaned.mean() - frame[3:-3].mean()) < 0.003


def test_clipped_mean_rejects_outliers_in_time():
    rng = np.random.default_rng(3)
    stack = (1000 + 30 * rng.standard_normal((4, 5, 9))).astype(np.float32)
    clean_mean = stack.mean(axis=-1)
    stack[2, 3, 4] = SATURATED
    result = clipped_mean_frames(stack, 5.0)
    assert abs(result[2, 3] - 1000) < 40
    changed = np.abs(result - clean_mean) > 1e-3
    changed[2, 3] = False
    assert np.count_nonzero(changed) <= 2


def test_combine_in_blocks_equals_one_block(stacks):
    """Blocks of 7 rows give the one-block result, but for the odd pixel at the spot limit
    (the noise behind the limit is estimated per block)."""
    files = tiff_files(stacks["sample"])
    for combine in ("median", "mean"):
        whole = combine_frames(files, combine)
        blocks = combine_frames(files, combine, block_bytes=N_SAMPLE * N_COLS * 4 * 7)
        assert np.count_nonzero(~np.isclose(blocks, whole, rtol=1e-6, atol=0)) <= 3
        np.testing.assert_allclose(blocks, whole, rtol=0.01)


# ---------------------------------------------------------------------------- profiles


@pytest.mark.parametrize("combine", ["median", "mean"])
def test_profile_recovers_the_true_profile(stacks, combine):
    profile = profile_from_stacks(**stacks, roi=ROI, pixel_um=PIXEL_UM, combine=combine)
    n_cols = ROI[3] - ROI[2]
    np.testing.assert_allclose(profile.x_um, np.arange(n_cols) * PIXEL_UM)
    assert profile.T.shape == profile.T_err.shape == (n_cols,)
    assert profile.image.shape == (N_ROWS, N_COLS)
    assert profile.roi == Roi(*ROI) and profile.angle_deg == 0.0
    assert 0.001 < np.median(profile.T_err) < 0.004
    assert_matches_truth(profile, truth())


@pytest.mark.parametrize("combine", ["median", "mean"])
def test_white_spots_do_not_leak(stacks, clean_stacks, combine):
    spotted = profile_from_stacks(**stacks, roi=ROI, pixel_um=PIXEL_UM, combine=combine)
    clean = profile_from_stacks(**clean_stacks, roi=ROI, pixel_um=PIXEL_UM, combine=combine)
    assert np.max(np.abs(spotted.T - clean.T) / clean.T_err) < 0.5
    spotted_files, clean_files = tiff_files(stacks["sample"]), tiff_files(clean_stacks["sample"])
    clean_image = combine_frames(clean_files, combine, spot_threshold=1e9)
    cleaned = combine_frames(spotted_files, combine)
    assert np.max(np.abs(cleaned - clean_image)) < 50  # counts; noise of one frame ~45
    if combine == "mean":  # the spots are there: without rejection a mean takes them in
        leaky = combine_frames(spotted_files, combine, spot_threshold=1e9)
        assert np.max(np.abs(leaky - clean_image)) > 1000


@pytest.mark.parametrize("tilt_deg", [0.5, -2.0])
def test_rotation_finds_the_tilt_and_recovers_the_profile(tmp_path, tilt_deg):
    specs = make_stacks(tmp_path, tilt_deg=tilt_deg, seed=5)
    profile = profile_from_stacks(**specs, roi=ROI, pixel_um=PIXEL_UM, rotate=True)
    assert profile.angle_deg == pytest.approx(tilt_deg, abs=0.12)
    np.testing.assert_allclose(profile.x_um, np.arange(ROI[3] - ROI[2]) * PIXEL_UM
                               * math.cos(math.radians(profile.angle_deg)))
    assert_matches_truth(profile, truth(tilt_deg))


@pytest.mark.parametrize("tilt_deg", [-4.0, -0.3, 0.0, 0.7, 2.5])
def test_edge_angle_without_noise(tilt_deg):
    assert edge_angle_deg(transmission_image(tilt_deg), Roi(*ROI)) == pytest.approx(
        tilt_deg, abs=0.01)


def test_rotation_without_an_edge_is_rejected():
    with pytest.raises(FwdfitError, match="found no edge"):
        edge_angle_deg(np.ones((N_ROWS, N_COLS)), Roi(*ROI))


def test_dose_correction(tmp_path):
    specs = make_stacks(tmp_path, dose=1.05, spots=False, seed=7)
    sample_free = (4, 60, 0, 12)  # columns 0..11: ROI coordinate u < 2, T = 1
    uncorrected = profile_from_stacks(**specs, roi=ROI, pixel_um=PIXEL_UM)
    assert np.median(uncorrected.T / truth()) == pytest.approx(1.05, abs=0.003)
    corrected = profile_from_stacks(**specs, roi=ROI, pixel_um=PIXEL_UM, dose_roi=sample_free)
    assert_matches_truth(corrected, truth())


def test_sheared_roi_interpolates_linearly_within_rows():
    rows, cols = np.mgrid[0:6, 0:9].astype(float)
    image = 3.0 + 2.0 * rows - 0.5 * cols
    roi = Roi(1, 5, 2, 8)  # centre row 2.5
    tilt = 0.3
    sheared = sheared_roi(image, roi, tilt)
    shift = (np.arange(1, 5) - 2.5) * tilt
    expected = 3.0 + 2.0 * rows[1:5, 2:8] - 0.5 * (cols[1:5, 2:8] + shift[:, None])
    np.testing.assert_allclose(sheared, expected)
    assert np.isnan(sheared_roi(image, Roi(0, 6, 0, 9), 0.3)[0, 0])


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("roi, message", [
    ((4, 70, 10, 190), "outside the image"),
    ((10, 10, 10, 190), "empty or outside"),
    ((-1, 10, 10, 190), "outside the image"),
    ((4, 5, 10, 190), "at least 2 rows"),
    ((4, 60, 10), "four integers"),
])
def test_bad_roi_is_rejected(stacks, roi, message):
    with pytest.raises(FwdfitError, match=message):
        profile_from_stacks(**stacks, roi=roi, pixel_um=PIXEL_UM)


def test_open_beam_darker_than_dark_is_rejected(stacks):
    with pytest.raises(FwdfitError, match=r"open beam darker than dark frame at 10080 pixels "
                                          r"of the region rows 4:60, columns 10:190"):
        profile_from_stacks(sample=stacks["sample"], open_beam=stacks["dark"],
                            dark=stacks["open_beam"], roi=ROI, pixel_um=PIXEL_UM)


def test_stacks_of_different_shapes_are_rejected(stacks, tmp_path):
    tifffile.imwrite(tmp_path / "dark.tif", np.zeros((N_ROWS, N_COLS + 1), np.uint16))
    with pytest.raises(FwdfitError, match="differ in shape.*dark 64x201"):
        profile_from_stacks(sample=stacks["sample"], open_beam=stacks["open_beam"],
                            dark=tmp_path / "dark.tif", roi=ROI, pixel_um=PIXEL_UM)


@pytest.mark.parametrize("pixel_um", [0.0, -2.4, math.nan])
def test_bad_pixel_size_is_rejected(stacks, pixel_um):
    with pytest.raises(FwdfitError, match="pixel_um must be positive"):
        profile_from_stacks(**stacks, roi=ROI, pixel_um=pixel_um)


# -------------------------------------------------------------------------------- CLI


def parse(argv):
    return build_parser().parse_args(argv)


def cli_args(stacks, out, *extra):
    return ["profile", "--sample", str(stacks["sample"]), "--open", str(stacks["open_beam"]),
            "--dark", str(stacks["dark"]), "--roi", ",".join(map(str, ROI)),
            "--pixel-um", str(PIXEL_UM), "--out", str(out), *extra]


def test_cli_writes_csv_and_png(stacks, tmp_path):
    out = tmp_path / "result" / "d08.5.csv"
    args = parse(cli_args(stacks, out, "--combine", "mean", "--dose-roi", "4,60,0,12"))
    args.handler(args)
    assert out.read_text().splitlines()[0] == "x_um,T,T_err"
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    assert table.shape == (ROI[3] - ROI[2], 3)
    expected = profile_from_stacks(**stacks, roi=ROI, pixel_um=PIXEL_UM, combine="mean",
                                   dose_roi=(4, 60, 0, 12))
    np.testing.assert_allclose(table[:, 1], expected.T, rtol=1e-8)
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in out.parent.iterdir()) == ["d08.5.csv", "d08.5.png"]


def test_write_profile_csv_round_trip(tmp_path):
    x_um, T, T_err = np.array([0.0, 2.4]), np.array([1.0, 0.75]), np.array([0.01, 0.02])
    write_profile_csv(tmp_path / "p.csv", x_um, T, T_err)
    table = np.loadtxt(tmp_path / "p.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(table, np.column_stack([x_um, T, T_err]))


@pytest.mark.parametrize("option, value, message", [
    ("--roi", "4,60,10", "--roi must be R0,R1,C0,C1"),
    ("--roi", "4,60,a,190", "--roi must be R0,R1,C0,C1"),
    ("--roi", "4,70,10,190", "outside the image"),
    ("--dose-roi", "0:12", "--dose-roi must be R0,R1,C0,C1"),
    ("--out", "profile.txt", "must name a .csv file"),
])
def test_cli_bad_input_writes_nothing(stacks, tmp_path, option, value, message):
    argv = cli_args(stacks, tmp_path / "profile.csv")
    if option in argv:
        argv[argv.index(option) + 1] = value
    else:
        argv += [option, value]
    if option == "--out":
        argv[argv.index(option) + 1] = str(tmp_path / value)
    args = parse(argv)
    with pytest.raises(FwdfitError, match=message):
        args.handler(args)
    assert list(tmp_path.iterdir()) == []
