"""Case 4 of issue 21, on logs of the independent plant (tests/sims/arm.py): implausible time
units and rates are refused in one line naming the file and the column; positions in degrees
are named."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from robid_link.exceptions import DataError, DataWarning
from robid_link.ident.data.logs import load_log
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL

from ..sims.arm import Noise
from ..sims.cases import plant_log, quiet


@pytest.mark.parametrize(("unit", "rate", "reads"), [
    ("ms", 250.0, "read as milliseconds it is 250 Hz"),  # today: accepted, zz_1 = 6.6e5
    ("us", 1000.0, "read as microseconds it is 1000 Hz"),
    ("ns", 1000.0, "read as nanoseconds it is 1000 Hz"),  # a rate of 1e-6 Hz
])
def test_time_not_in_seconds_is_refused_naming_file_and_column(arm3, tmp_path, unit, rate,
                                                                reads):
    path, _ = plant_log(arm3, tmp_path / f"t_{unit}.csv", rate_hz=rate, duration_s=4.0,
                        time_unit=unit)
    with pytest.raises(DataError) as err:
        load_log(path, 3)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{path}: column t: ")
    assert reads in text and "give the time in seconds" in text


def test_npz_times_in_microseconds_name_their_array(arm3, tmp_path):
    _, rec = plant_log(arm3, tmp_path / "x.csv", rate_hz=500.0, duration_s=2.0)
    path = tmp_path / "x.npz"
    np.savez(path, times=rec.t * 1e6, positions=rec.q, torques=rec.tau)
    with pytest.raises(DataError, match=r"x\.npz: array 'times': .* read as microseconds"):
        load_log(path, 3)


def test_mat_rate_given_as_a_step_is_refused(tmp_path):
    import scipy.io

    path = tmp_path / "m.mat"
    scipy.io.savemat(path, {"m": np.zeros((50, 12))})
    with pytest.raises(DataError, match=r"--fs 0\.001: a robot's log runs at"):
        load_log(path, 3, fs=0.001)


def test_seconds_at_250_hz_to_4_khz_are_accepted(arm3, tmp_path):
    for rate in (250.0, 4000.0):
        path, _ = plant_log(arm3, tmp_path / f"s{rate:g}.csv", rate_hz=rate, duration_s=1.0)
        assert load_log(path, 3).fs == pytest.approx(rate, rel=1e-6)


def test_milliseconds_at_a_rate_the_rate_check_allows_are_named(arm3, tmp_path):
    """10 kHz in milliseconds reads as 10 Hz, a rate a log may have: the motion then crawls
    at a thousandth of its speed, and the checks say so."""
    path, _ = plant_log(arm3, tmp_path / "ms10k.csv", rate_hz=10_000.0, duration_s=6.0,
                        time_unit="ms", noise=Noise(0.05))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = identify(arm3, load_logs(arm3, [path]), DEFAULT_MODEL, cutoff_hz=2.0)
    crawl = [n for n in res.notes if "crawls" in n]
    assert crawl and "is the time column in seconds?" in crawl[0]
    assert any(issubclass(w.category, DataWarning) and "crawls" in str(w.message)
               for w in caught)


def test_positions_in_degrees_are_named(arm3, tmp_path):
    path, _ = plant_log(arm3, tmp_path / "deg.csv", duration_s=20.0, degrees=True)
    with warnings.catch_warnings():
        quiet()
        res = identify(arm3, load_logs(arm3, [path]), DEFAULT_MODEL)
    assert any("looks like degrees (the log must be in rad)" in n for n in res.notes), res.notes
