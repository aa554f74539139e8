"""``fwdfit profile --tof``: time-of-flight stacks (FITS folders with ``*_Spectra.txt``,
NeXus/HDF5 histograms) written here with a known transmission per bin, turned into one
profile per wavelength bin; bad input refused in one line with nothing written."""

from __future__ import annotations

import sys
from pathlib import Path

import h5py  # the tof extra, installed with the test extra
import numpy as np
import pytest
from astropy.io import fits

from fwdfit.cli import main

import tomllib

H_OVER_MN = 3956.034  # m Å / s, the de Broglie constant the command must use
N_BINS, N_ROWS, N_COLS = 12, 40, 32
EDGE_COL = 16  # the sample covers columns 16 and up
OPEN_COUNTS, DARK_COUNTS = 2000.0, 20.0
CENTRES_S = 5e-3 + 4e-4 * np.arange(N_BINS)  # bin centres written to the files, s
FLIGHT_PATH_M = 10.0
ROI = (5, 35, 2, 30)  # rows 5:35, columns 2:30


def true_T(n_bins: int = N_BINS) -> np.ndarray:
    """``(n_bins, N_COLS)``: 1 left of the edge, falling with wavelength behind the sample."""
    T = np.ones((n_bins, N_COLS))
    T[:, EDGE_COL:] = (0.8 - 0.03 * np.arange(n_bins))[:, None]
    return T


def counts(seed: int, with_dark: bool = True) -> dict[str, np.ndarray]:
    """Poisson counts ``(N_BINS, N_ROWS, N_COLS)`` of sample, open beam and dark."""
    rng = np.random.default_rng(seed)
    dark = DARK_COUNTS if with_dark else 0.0
    shape = (N_BINS, N_ROWS, N_COLS)
    stacks = {"sample": rng.poisson(OPEN_COUNTS * true_T()[:, None, :] + dark, shape),
              "open": rng.poisson(OPEN_COUNTS + dark, shape)}
    if with_dark:
        stacks["dark"] = rng.poisson(dark, shape)
    return {name: values.astype(np.uint16) for name, values in stacks.items()}


def write_fits_folder(folder: Path, stack: np.ndarray, times_s=CENTRES_S) -> Path:
    """One FITS per bin as MCP cameras write them, a summed image and ``_Spectra.txt``
    (headerless, tab-separated, CRLF: time of flight in s, counts)."""
    folder.mkdir(parents=True)
    for index, image in enumerate(stack):
        fits.PrimaryHDU(image).writeto(folder / f"run_{index:05d}.fits")
    fits.PrimaryHDU(stack.sum(axis=0).astype(np.uint32)).writeto(folder / "run_SummedImg.fits")
    rows = [f"{t:.6E}\t{int(image.sum())}" for t, image in zip(times_s, stack)]
    (folder / "run_Spectra.txt").write_bytes(("\r\n".join(rows) + "\r\n").encode())
    return folder


def write_nexus(path: Path, stack: np.ndarray, tof_last: bool = False,
                centres_s: np.ndarray = CENTRES_S) -> Path:
    """A NeXus file: /entry/data (NXdata, signal counts) with time_of_flight edges in
    microseconds; bins first, or last (``tof_last``) as NXdetector data often are."""
    edges_us = 1e6 * midpoint_edges(centres_s)
    with h5py.File(path, "w") as handle:
        handle.attrs["default"] = "entry"
        entry = handle.create_group("entry")
        entry.attrs.update({"NX_class": "NXentry", "default": "data"})
        data = entry.create_group("data")
        values = np.moveaxis(stack, 0, -1) if tof_last else stack
        axes = [".", ".", "time_of_flight"] if tof_last else ["time_of_flight", ".", "."]
        data.attrs.update({"NX_class": "NXdata", "signal": "counts", "axes": axes})
        data.create_dataset("counts", data=values.astype(np.int32))
        data.create_dataset("time_of_flight", data=edges_us).attrs["units"] = "microsecond"
    return path


def midpoint_edges(centres: np.ndarray) -> np.ndarray:
    middle = (centres[1:] + centres[:-1]) / 2
    return np.concatenate([[2 * centres[0] - middle[0]], middle, [2 * centres[-1] - middle[-1]]])


def tof_args(sample, open_beam, dark, out, *extra) -> list[str]:
    args = ["profile", "--tof", "--sample", str(sample), "--open", str(open_beam),
            "--roi", ",".join(map(str, ROI)), "--pixel-um", "55", "--out", str(out),
            "--flight-path-m", str(FLIGHT_PATH_M)]
    return args + (["--dark", str(dark)] if dark is not None else []) + list(extra)


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path) as stream:
        names = stream.readline().strip().split(",")
        values = np.loadtxt(stream, delimiter=",", ndmin=2)
    return {name: values[:, i] for i, name in enumerate(names)}


def read_bins(out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """``(x_um, T, T_err)`` of every bin in order and the wavelengths table."""
    table = read_csv(out / "wavelengths.csv")
    names = [f"bin{int(i):03d}" for i in table["bin"]]
    profiles = [read_csv(out / f"{name}.csv") for name in names]
    return (profiles[0]["x_um"], np.array([p["T"] for p in profiles]),
            np.array([p["T_err"] for p in profiles]), table)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("fwdfit: error: "), err
    return err.strip()


@pytest.fixture(scope="module")
def stacks():
    return counts(seed=1)


@pytest.fixture()
def fits_dirs(tmp_path, stacks):
    return {name: write_fits_folder(tmp_path / name, stack) for name, stack in stacks.items()}


# ------------------------------------------------------------------------- the truth


def check_against_truth(out: Path, offset_us: float = 0.0) -> None:
    """Profiles within noise of the truth; wavelengths from lambda = (h/m_n) t / L."""
    x_um, T, T_err, table = read_bins(out)
    cols = slice(ROI[2], ROI[3])
    np.testing.assert_allclose(x_um, 55.0 * np.arange(ROI[3] - ROI[2]))
    pulls = (T - true_T()[:, cols]) / T_err
    # T_err from 30 rows: pulls are Student-t with 29 degrees of freedom.
    assert 0.75 < np.mean(pulls**2) < 1.3, np.mean(pulls**2)
    assert np.max(np.abs(pulls)) < 5.0
    # The Poisson error of a plateau pixel, over sqrt(rows): T_err is the right size.
    rows = ROI[1] - ROI[0]
    expected = np.sqrt(true_T()[:, cols] * (1 + true_T()[:, cols]) / OPEN_COUNTS / rows)
    assert 0.75 < np.median(T_err / expected) < 1.25
    edges_s = midpoint_edges(CENTRES_S) + offset_us * 1e-6
    np.testing.assert_allclose(table["lambda_min_A"], H_OVER_MN * edges_s[:-1] / FLIGHT_PATH_M,
                               rtol=1e-8)
    np.testing.assert_allclose(table["lambda_max_A"], H_OVER_MN * edges_s[1:] / FLIGHT_PATH_M,
                               rtol=1e-8)
    np.testing.assert_allclose(table["tof_min_us"], 1e6 * edges_s[:-1], rtol=1e-8)


def test_fits_folders_give_the_true_profiles_and_wavelengths(fits_dirs, tmp_path, capsys):
    out = tmp_path / "bins"
    assert main(tof_args(fits_dirs["sample"], fits_dirs["open"], fits_dirs["dark"], out,
                         "--tof-offset-us", "-150")) == 0
    assert "wrote 12 wavelength bins" in capsys.readouterr().out
    check_against_truth(out, offset_us=-150.0)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"bin{i:03d}.csv" for i in range(N_BINS)] + ["wavelengths.csv", "scene.toml", ".fwdfit-output"])


@pytest.mark.parametrize("tof_last", [False, True])
def test_nexus_histograms_give_the_same_profiles_as_fits(stacks, fits_dirs, tmp_path, tof_last):
    """The NeXus default signal and its time_of_flight axis (edges, microseconds), bins
    first or last, give exactly the profiles of the same counts as FITS folders."""
    files = {name: write_nexus(tmp_path / f"{name}.nxs", stack, tof_last)
             for name, stack in stacks.items()}
    assert main(tof_args(files["sample"], files["open"], files["dark"], tmp_path / "h5")) == 0
    assert main(tof_args(fits_dirs["sample"], fits_dirs["open"], fits_dirs["dark"],
                         tmp_path / "fits")) == 0
    check_against_truth(tmp_path / "h5")
    for name in ["bin000.csv", "bin011.csv", "wavelengths.csv"]:
        np.testing.assert_allclose(read_csv(tmp_path / "h5" / name)["T" if "bin" in name
                                                                    else "lambda_max_A"],
                                   read_csv(tmp_path / "fits" / name)["T" if "bin" in name
                                                                      else "lambda_max_A"],
                                   rtol=1e-9)


def test_named_datasets_centres_in_seconds_and_no_dark(tmp_path):
    """--dataset and --tof-dataset name a plain HDF5 layout (no NeXus attributes), bin
    centres in seconds; without a dark stack T = S / O; Poisson errors from the counts."""
    stacks = counts(seed=2, with_dark=False)
    paths = {}
    for name, stack in stacks.items():
        paths[name] = tmp_path / f"{name}.h5"
        with h5py.File(paths[name], "w") as handle:
            handle.create_dataset("raw/images", data=stack)
            handle.create_dataset("raw/t", data=CENTRES_S).attrs["units"] = "s"
    out = tmp_path / "out"
    assert main(tof_args(paths["sample"], paths["open"], None, out, "--dataset", "raw/images",
                         "--tof-dataset", "raw/t", "--errors", "counts")) == 0
    check_against_truth(out)
    # Poisson errors by hand: var T = S / O^2 + S^2 / O^3 per pixel, mean over the rows.
    _, T, T_err, _ = read_bins(out)
    S, O = (stacks[n][:, ROI[0]:ROI[1], ROI[2]:ROI[3]].astype(float) for n in ("sample", "open"))
    np.testing.assert_allclose(T, (S / O).mean(axis=1), rtol=1e-9)
    by_hand = np.sqrt((S / O**2 + S**2 / O**3).sum(axis=1)) / S.shape[1]
    np.testing.assert_allclose(T_err, by_hand, rtol=1e-9)


def test_rebin_sums_every_bin_once(stacks, fits_dirs, tmp_path):
    """--rebin 5 of 12 bins: groups 0-4, 5-9, 10-11 (the rest), each normalised from the
    summed counts, edges those of the groups' outer bins."""
    out = tmp_path / "rebinned"
    assert main(tof_args(fits_dirs["sample"], fits_dirs["open"], fits_dirs["dark"], out,
                         "--rebin", "5")) == 0
    _, T, _, table = read_bins(out)
    groups = [(0, 5), (5, 10), (10, 12)]
    assert T.shape[0] == len(groups)
    roi = (slice(None), slice(ROI[0], ROI[1]), slice(ROI[2], ROI[3]))
    S, O, D = (stacks[n][roi].astype(float) for n in ("sample", "open", "dark"))
    for row, (a, b) in zip(T, groups):
        summed = {name: values[a:b].sum(axis=0) for name, values in zip("SOD", (S, O, D))}
        assert sum(v.sum() for v in summed.values()) == pytest.approx(
            S[a:b].sum() + O[a:b].sum() + D[a:b].sum())  # counts conserved
        by_hand = ((summed["S"] - summed["D"]) / (summed["O"] - summed["D"])).mean(axis=0)
        np.testing.assert_allclose(row, by_hand, rtol=1e-9)
    edges_A = H_OVER_MN * midpoint_edges(CENTRES_S) / FLIGHT_PATH_M
    np.testing.assert_allclose(table["lambda_min_A"], edges_A[[0, 5, 10]], rtol=1e-8)
    np.testing.assert_allclose(table["lambda_max_A"], edges_A[[5, 10, 12]], rtol=1e-8)


def test_scene_skeleton_names_every_bin(fits_dirs, tmp_path):
    out = tmp_path / "bins"
    assert main(tof_args(fits_dirs["sample"], fits_dirs["open"], fits_dirs["dark"], out,
                         "--distance-mm", "12.5", "--rebin", "4")) == 0
    with open(out / "scene.toml", "rb") as stream:
        scene = tomllib.load(stream)
    table = read_csv(out / "wavelengths.csv")
    names = ["bin000", "bin001", "bin002"]
    assert scene["instrument"] == {"pixel_um": 55.0}
    assert list(scene["spectra"]) == names
    for name, low, high in zip(names, table["lambda_min_A"], table["lambda_max_A"]):
        assert scene["spectra"][name]["lambda_min_A"] == pytest.approx(low, rel=1e-8)
        assert scene["spectra"][name]["lambda_max_A"] == pytest.approx(high, rel=1e-8)
    assert scene["profiles"] == [{"name": n, "spectrum": n, "file": f"{n}.csv",
                                  "distance_mm": 12.5} for n in names]
    assert all((out / p["file"]).is_file() for p in scene["profiles"])


def test_rotate_and_dose_roi_recover_a_tilted_edge(tmp_path):
    """An edge tilted by 2 degrees and an open beam 10 % brighter than the sample's: the
    angle is found once (in the sum over bins) and every bin's plateaus come out true."""
    angle_deg, rows = 2.0, np.arange(N_ROWS)[:, None]
    centre_row = (ROI[0] + ROI[1] - 1) / 2
    edge = EDGE_COL - 0.5 + (rows - centre_row) * np.tan(np.radians(angle_deg))
    covered = np.clip(np.arange(N_COLS)[None, :] + 0.5 - edge, 0, 1)  # pixel fraction
    T_sample = 0.8 - 0.03 * np.arange(N_BINS)
    T = 1 - covered[None] + covered[None] * T_sample[:, None, None]
    rng = np.random.default_rng(3)
    beam = 50000.0
    files = {}
    for name, mean in (("sample", beam * T), ("open", 1.1 * beam * np.ones_like(T))):
        files[name] = write_nexus(tmp_path / f"{name}.nxs", rng.poisson(mean))
    out = tmp_path / "out"
    assert main(tof_args(files["sample"], files["open"], None, out, "--rotate",
                         "--dose-roi", "5,35,2,10")) == 0
    header = (out / "scene.toml").read_text().splitlines()[1]
    found = float(header.split("rotated by ")[1].split(" deg")[0])
    assert found == pytest.approx(angle_deg, abs=0.05), found
    x_um, T_out, T_err, _ = read_bins(out)
    columns = np.arange(ROI[2], ROI[3])
    left, right = columns < EDGE_COL - 2, columns > EDGE_COL + 2
    pulls_left = (T_out[:, left] - 1.0) / T_err[:, left]
    pulls_right = (T_out[:, right] - T_sample[:, None]) / T_err[:, right]
    assert np.max(np.abs(pulls_left)) < 5 and np.max(np.abs(pulls_right)) < 5
    np.testing.assert_allclose(np.diff(x_um), 55.0 * np.cos(np.radians(found)), rtol=1e-6)


# ------------------------------------------------------------------------ bad input


def _remove(path: Path) -> None:
    path.unlink()


BAD_FITS = {
    # case: (edit of the FITS folders, extra options, words the message must hold)
    "missing_middle_bin": (lambda d: _remove(d["sample"] / "run_00004.fits"), [],
                           "frames missing or repeated: number 3 is followed by 5"),
    "missing_last_bin": (lambda d: _remove(d["open"] / "run_00011.fits"), [],
                         "run_Spectra.txt has 12 bin times but"),
    "spectra_row_too_many": (
        lambda d: (d["sample"] / "run_Spectra.txt").write_text(
            (d["sample"] / "run_Spectra.txt").read_text() + "9.9E-03\t5\n"), [],
        "has 13 bin times but"),
    "no_spectra_file": (lambda d: _remove(d["dark"] / "run_Spectra.txt"), [],
                        "no *_Spectra.txt files"),
    "spectra_not_numbers": (lambda d: (d["sample"] / "run_Spectra.txt").write_text("t\tc\n"), [],
                            "cannot read spectra file"),
    "shape_mismatch": (lambda d: [fits.PrimaryHDU(np.ones((40, 30), np.uint16)).writeto(
        p, overwrite=True) for p in sorted(d["open"].glob("run_0*.fits"))], [],
        "sample and open beam images differ in shape: 40x32"),
    "frame_shape_differs": (lambda d: fits.PrimaryHDU(np.ones((40, 30), np.uint16)).writeto(
        d["sample"] / "run_00003.fits", overwrite=True), [], "FITS frames differ in shape"),
    "bins_differ_in_time": (
        lambda d: (d["open"] / "run_Spectra.txt").write_text(
            "\n".join(f"{t * 1.01:.6E}\t1" for t in CENTRES_S)), [],
        "sample and open beam bins differ in time of flight"),
    "unreadable_fits": (lambda d: (d["sample"] / "run_00002.fits").write_bytes(b"not FITS" * 99),
                        [], "cannot read FITS file"),
    "no_flight_path": (None, ["--flight-path-m"], "--tof needs --flight-path-m"),
    "negative_flight_path": (None, ["--flight-path-m", "-3"], "--flight-path-m must be a positive"),
    "nan_flight_path": (None, ["--flight-path-m", "nan"], "--flight-path-m must be a positive"),
    "text_flight_path": (None, ["--flight-path-m", "ten"], "argument --flight-path-m: invalid"),
    "offset_before_pulse": (None, ["--tof-offset-us", "-6000"], "check --tof-offset-us"),
    "zero_rebin": (None, ["--rebin", "0"], "--rebin must be a positive integer"),
    "combine_with_tof": (None, ["--combine", "mean"], "--combine does not apply with --tof"),
    "counts_with_rotate": (None, ["--errors", "counts", "--rotate"], "cannot be used with --rotate"),
    "dataset_for_fits": (None, ["--dataset", "x"], "apply to HDF5 files"),
    "roi_outside": (None, ["--roi", "0,50,0,10"], "outside the image"),
}


@pytest.mark.parametrize("case", list(BAD_FITS))
def test_bad_fits_input_is_one_line_and_writes_nothing(fits_dirs, tmp_path, capsys, case):
    edit, extra, words = BAD_FITS[case]
    if edit is not None:
        edit(fits_dirs)
    args = tof_args(fits_dirs["sample"], fits_dirs["open"], fits_dirs["dark"],
                    tmp_path / "res" / "out")
    if extra == ["--flight-path-m"]:  # drop the option and its value
        index = args.index("--flight-path-m")
        del args[index:index + 2]
    elif extra[:1] == ["--flight-path-m"] or extra[:1] == ["--roi"]:
        args[args.index(extra[0]) + 1] = extra[1]
    else:
        args += extra
    assert main(args) == 1
    assert words in one_error_line(capsys)
    assert not (tmp_path / "res").exists()


def test_bad_hdf5_input_is_one_line_and_writes_nothing(stacks, tmp_path, capsys):
    files = {name: write_nexus(tmp_path / f"{name}.nxs", stack) for name, stack in stacks.items()}
    out = tmp_path / "out"
    broken = tmp_path / "broken.h5"
    broken.write_bytes(b"\x89HDF\r\n" + b"\0" * 200)
    cases = [
        (tof_args(broken, files["open"], None, out), "cannot read HDF5 file"),
        (tof_args(files["sample"], files["open"], None, out, "--dataset", "entry/nothing"),
         "no dataset entry/nothing (--dataset)"),
        (tof_args(files["sample"], files["open"], None, out, "--dataset", "entry/data/time_of_flight"),
         "not (bins, rows, columns)"),
        (tof_args(files["sample"], tmp_path / "none.nxs", None, out), "no such file or folder"),
        (tof_args(files["sample"], tmp_path / "open.txt", None, out), "no such file or folder"),
    ]
    with h5py.File(tmp_path / "plain.h5", "w") as handle:
        handle.create_dataset("images", data=stacks["open"])
    cases.append((tof_args(files["sample"], tmp_path / "plain.h5", None, out),
                  "no NeXus NXdata group with a signal; name the histogram with --dataset"))
    with h5py.File(tmp_path / "units.h5", "w") as handle:
        handle.create_dataset("images", data=stacks["open"])
        handle.create_dataset("t", data=CENTRES_S).attrs["units"] = "furlong"
    cases.append((tof_args(tmp_path / "units.h5", tmp_path / "units.h5", None, out,
                           "--dataset", "images", "--tof-dataset", "t"), "not a time unit"))
    write_nexus(tmp_path / "short.nxs", stacks["open"][:11], centres_s=CENTRES_S[:11])
    cases.append((tof_args(files["sample"], tmp_path / "short.nxs", None, out),
                  "sample has 12 time bins"))
    for args, words in cases:
        assert main(args) == 1, words
        line = one_error_line(capsys)
        assert words in line, line
        assert not out.exists()


def test_tof_options_without_tof_and_missing_extra(fits_dirs, tmp_path, capsys, monkeypatch):
    """TOF-only options are refused without --tof; without h5py the error names the extra."""
    tiff_args = ["profile", "--sample", "s.tif", "--open", "o.tif", "--dark", "d.tif",
                 "--roi", "0,2,0,4", "--pixel-um", "2", "--out", str(tmp_path / "p.csv")]
    assert main(tiff_args + ["--rebin", "2"]) == 1
    assert "--rebin applies to --tof only" in one_error_line(capsys)
    assert main(tiff_args[:5] + tiff_args[7:]) == 1
    assert "required: --dark" in one_error_line(capsys)
    monkeypatch.setitem(sys.modules, "h5py", None)  # import h5py raises ImportError
    out = tmp_path / "out"
    (tmp_path / "s.nxs").write_bytes(b"")
    assert main(tof_args(tmp_path / "s.nxs", tmp_path / "s.nxs", None, out)) == 1
    assert "reading HDF5 needs h5py: pip install 'fwdfit[tof]'" in one_error_line(capsys)
    assert not out.exists()


def test_ctrl_c_and_a_non_empty_out_folder_leave_nothing(fits_dirs, tmp_path, capsys,
                                                         monkeypatch):
    """Ctrl-C while writing the bins leaves neither the folder nor temporary files; a
    non-empty --out folder is refused and left as it was."""
    def args(out):
        return tof_args(fits_dirs["sample"], fits_dirs["open"], None, out)

    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "mine.txt").write_text("keep")
    assert main(args(taken)) == 1
    assert "holds files that fwdfit did not write" in one_error_line(capsys)
    assert [p.name for p in taken.iterdir()] == ["mine.txt"]
    calls = []

    def interrupt(*a, **k):
        calls.append(a)
        if len(calls) == 3:
            raise KeyboardInterrupt

    monkeypatch.setattr(np, "savetxt", interrupt)
    out = tmp_path / "bins"
    assert main(args(out)) == 130
    assert capsys.readouterr().err == "fwdfit: interrupted\n"
    assert not out.exists() and len(calls) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dark", "open", "sample", "taken"]
