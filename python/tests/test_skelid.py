"""skelid from Python, against the same truth as the Rust tests: an analytic damped chirp,
the demo campaign identified by the command line (same code path, so the same numbers to
the last bit), and the gap's verdict on the demo's friction run.

Run by scripts/test-python.sh (the README's test command), which builds the package with
pip and names the command line's binary in SKELID_BIN."""

import json
import math
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import skelid

FS = 1000.0


def cli(*args):
    binary = os.environ.get("SKELID_BIN") or shutil.which("skelid")
    if not binary:
        pytest.fail("no skelid binary: run scripts/test-python.sh, or set SKELID_BIN")
    return subprocess.run([binary, *map(str, args)], capture_output=True, text=True)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo campaign, and `skelid run --backend cpu` over it (summary rows)."""
    d = tmp_path_factory.mktemp("demo")
    r = cli("demo", "--out", d / "demo")
    assert r.returncode == 0, r.stderr
    archive = d / "demo" / "demo_campaign.h5"
    r = cli("run", archive, "--backend", "cpu", "--quiet", "--out", d / "run")
    assert r.returncode in (0, 1), r.stderr
    rows = json.loads((d / "run" / "summary.json").read_text())["rows"]
    return archive, rows


def damped_chirp(seconds=10.0):
    """A = e^(-0.1 t), f = 20 + 1.5 t Hz: the truth of the envelope and the frequency."""
    t = np.arange(int(FS * seconds)) / FS
    amplitude = np.exp(-0.1 * t)
    frequency = 20.0 + 1.5 * t
    x = amplitude * np.cos(2 * np.pi * (20.0 * t + 0.75 * t**2))
    return x, amplitude, frequency


def test_version_is_the_crates():
    assert skelid.__version__ == "0.1.0"
    assert issubclass(skelid.SkelidError, Exception)


def test_wavelet_track_of_a_damped_chirp_is_its_envelope_and_frequency():
    x, amplitude, frequency = damped_chirp()
    r = skelid.track(x, FS, backend="cpu")
    for key in ("time", "amplitude", "frequency", "phase", "valid"):
        assert isinstance(r[key], np.ndarray) and r[key].shape == x.shape, key
    assert r["valid"].dtype == np.bool_
    assert r["method"] == "wavelet" and r["backend"] == "cpu"
    np.testing.assert_allclose(r["time"], np.arange(x.size) / FS)
    v = r["valid"]
    assert v.mean() > 0.8, v.mean()
    env = np.abs(r["amplitude"][v] / amplitude[v] - 1)
    assert env.max() < 0.01, env.max()
    freq = np.abs(r["frequency"][v] - frequency[v])
    assert freq.max() < 0.05, freq.max()


def test_hilbert_track_and_float32_and_strided_input():
    x, amplitude, frequency = damped_chirp()
    h = skelid.track(x, FS, method="hilbert")
    inner = slice(x.size // 10, 9 * x.size // 10)
    env = np.abs(h["amplitude"][inner] / amplitude[inner] - 1)
    assert env.max() < 0.02, env.max()
    assert np.abs(h["frequency"][inner] - frequency[inner]).max() < 0.1
    # float32 samples are converted: the same track to float32's resolution.
    w64 = skelid.track(x, FS, backend="cpu")
    w32 = skelid.track(x.astype(np.float32), FS, backend="cpu")
    v = w64["valid"] & w32["valid"]
    np.testing.assert_allclose(w32["amplitude"][v], w64["amplitude"][v], rtol=1e-5)
    # A strided view (every second sample) is the same signal at half the rate.
    half = skelid.track(x[::2], FS / 2, backend="cpu")
    assert half["amplitude"].size == x[::2].size
    with pytest.raises(ValueError, match="method"):
        skelid.track(x, FS, method="fourier")
    with pytest.raises(ValueError, match="scales"):
        skelid.track(x, FS, scales=2)


def test_identify_gives_the_command_lines_numbers_on_the_demo(demo):
    archive, rows = demo
    runs = skelid.read_campaign(archive)
    assert len(runs) == 11
    compared = 0
    for run in runs:
        for method in ("wavelet", "hilbert"):
            row = next(r for r in rows if r["run"] == run["path"] and r["method"] == method)
            try:
                res = skelid.identify(
                    run["input"],
                    run["output"],
                    run["sample_rate"],
                    kind=run["kind"],
                    method=method,
                    inertia=run["inertia"],
                    gravity_stiffness=run["gravity_stiffness"],
                    input_quantity=run["input_quantity"],
                    output_quantity=run["output_quantity"],
                    units=run["units"],
                    mode_band=run["mode_band"],
                    mode_near=run["mode_near"],
                    backend="cpu",
                )
            except skelid.SkelidError as e:
                assert row["status"] == "failed", (run["path"], method, e)
                assert str(e) in row["error"], (str(e), row["error"])
                continue
            assert row["status"] == "ok", (run["path"], method, row["error"])
            for name, value in res["parameters"].items():
                expected = row[name]
                if expected is None:
                    assert math.isnan(value), (run["path"], method, name, value)
                else:
                    assert value == expected, (run["path"], method, name, value, expected)
                compared += 1
            assert res["units"]["clearance"] == row["units"]["clearance"]
            sk = res["skeleton"]
            assert sk["amplitude"].size == sk["natural_frequency"].size > 0
    print(f"{compared} parameters equal to the command line's")
    assert compared > 300, compared


def test_identify_recovers_the_paper_rigs_clearance(demo):
    archive, _ = demo
    (run,) = skelid.read_campaign(archive, runs="/demo/paper_rig")
    res = skelid.identify(
        run["input"], run["output"], run["sample_rate"], inertia=run["inertia"], units=run["units"]
    )
    # The demo's rig: 0.0262 rad of total clearance.
    clearance = res["parameters"]["clearance"]
    assert abs(clearance / 0.0262 - 1) < 0.05, clearance
    assert res["parameters"]["clearance_stderr"] > 0
    assert res["units"]["clearance"] == "rad"
    with pytest.raises(ValueError, match="same length"):
        skelid.identify(run["input"][:-1], run["output"], run["sample_rate"])
    with pytest.raises(ValueError, match="needs its input"):
        skelid.identify(None, run["output"], run["sample_rate"])


def test_gap_names_the_missing_friction_as_the_command_line_does(demo, tmp_path):
    archive, _ = demo
    (run,) = skelid.read_campaign(archive, runs="/demo/effects/coulomb_friction")
    model = {"inertia": 3.16, "stiffness": 15000.0, "damping": 13.0, "clearance": 0.0262}
    options = dict(baseline_evaluations=40, candidate_evaluations=20, pairs=False)
    effects = ["coulomb_friction", "sensor_delay"]
    doc = skelid.gap(model, run["input"], run["output"], run["sample_rate"], effects=effects, **options)
    assert doc["format"] == "skelid-gap/1" and doc["failed"] == []
    assert doc["settings"]["baseline_evaluations"] == 40
    (g,) = doc["runs"]
    assert g["run"] == "/python"
    assert g["verdict"] == "coulomb_friction", g["verdict"]
    assert [c["effect"] for c in g["candidates"]][0] == "coulomb_friction"
    # The command line on the same run, with the same options, says the same.
    rig = tmp_path / "rig.toml"
    rig.write_text("".join(f"{k} = {v}\n" for k, v in model.items()))
    r = cli(
        "gap", "--model", rig, archive, "--run", "/demo/effects/coulomb_friction",
        "--baseline-evaluations", 40, "--candidate-evaluations", 20, "--no-pairs",
        "--effects", ",".join(effects), "--backend", "cpu", "--out", tmp_path / "gap",
    )
    assert r.returncode == 0, r.stderr
    (expected,) = json.loads((tmp_path / "gap" / "gap.json").read_text())["runs"]
    for key in ("nominal_gap", "baseline_gap", "verdict"):
        assert g[key] == expected[key], key
    assert [c["gap_holdout"] for c in g["candidates"]] == [
        c["gap_holdout"] for c in expected["candidates"]
    ]
    # The waveform domain by default, as `skelid gap`; left out on request
    # (`skelid gap --no-waveform`).
    assert doc["settings"]["waveform"] is True
    # The model's own effects held in the baseline unless asked (`--refit-effects`).
    assert doc["settings"]["refit_effects"] is False
    assert all(isinstance(c["domains"]["waveform"], float) for c in g["candidates"])
    w = skelid.gap(
        model, run["input"], run["output"], run["sample_rate"],
        effects=["coulomb_friction"], waveform=False, **options,
    )
    assert w["settings"]["waveform"] is False
    assert all("waveform" not in c["domains"] for c in w["runs"][0]["candidates"])
    # A model as TOML text or a path is the same model.
    g2 = skelid.gap(str(rig), run["input"], run["output"], run["sample_rate"], effects=effects, **options)
    assert g2["runs"][0]["baseline_gap"] == g["baseline_gap"]
    with pytest.raises(skelid.SkelidError, match="stiffness"):
        skelid.gap("inertia = 3.16\n", run["input"], run["output"], run["sample_rate"])


def test_read_campaign_raises_the_command_lines_errors(tmp_path):
    missing = tmp_path / "nope.h5"
    with pytest.raises(skelid.SkelidError) as e:
        skelid.read_campaign(missing)
    r = cli("inspect", missing)
    assert r.returncode != 0
    assert str(e.value) in r.stderr, (str(e.value), r.stderr)
    text = tmp_path / "notes.h5"
    text.write_text("not an archive")
    with pytest.raises(skelid.SkelidError) as e:
        skelid.read_campaign(text)
    # `inspect` lists an archive's problems on stdout, with exit status 1.
    r = cli("inspect", text)
    assert r.returncode == 1
    assert str(e.value) in r.stdout, (str(e.value), r.stdout)
    with pytest.raises(ValueError, match="errors"):
        skelid.read_campaign(missing, errors="ignore")


def test_read_campaign_of_a_folder_passes_over_skelids_own_results(demo):
    archive, _ = demo
    folder = archive.parent  # the demo's folder: its campaign and its results.h5
    assert (folder / "results.h5").exists() and (folder / "manifest.json").exists()
    runs = skelid.read_campaign(folder)
    assert len(runs) == 11
    assert {r["path"] for r in runs} == {r["path"] for r in skelid.read_campaign(archive)}
    with pytest.raises(skelid.SkelidError, match="skelid's own output, format skelid-results/1"):
        skelid.read_campaign(folder / "results.h5")
