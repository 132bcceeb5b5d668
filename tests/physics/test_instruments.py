"""The instruments against closed forms (Parseval, a line's bin, a Gaussian pulse's
autocorrelation), their noise, their settings' errors, and the measured reward against the
paper's r on settled states."""
import math

import pytest
import torch

from laserrl.physics import CavityParams, sech_fields
from laserrl.physics.instruments import Instruments, measure, measured_reward, spectrum_matrix
from laserrl.physics.observables import kurtosis

P = CavityParams()
QUIET = dict(spectrum_noise=0.0, spectrum_floor=0.0, energy_noise=0.0, autocorrelation_noise=0.0)
BAND = 2 * math.pi * P.n / P.T


def _line(w0: float, amplitude: float = 0.5):
    """A continuous wave at frequency w0 (a grid mode), in u only."""
    t = P.time_grid()
    u = (amplitude * torch.exp(1j * w0 * t)).to(torch.complex128)[None]  # U(w) = int u exp(-i w t) dt peaks at w0
    return u, torch.zeros_like(u)


def test_the_whole_band_holds_the_energy_and_the_power_meter_reads_it():
    u, v = sech_fields(3, P, amplitude=0.7, dtype=torch.complex128)
    v = v * torch.exp(torch.tensor(0.3j, dtype=torch.complex128))  # phase does not change a power
    m = measure(u, v, P, Instruments(spectrum_span=BAND, spectrum_bins=256, **QUIET))
    periodic = ((u.abs() ** 2 + v.abs() ** 2).sum(-1) * P.dt)  # Parseval holds for the periodic sum
    assert torch.allclose(m.spectrum.sum(-1), periodic, rtol=1e-10)
    assert torch.allclose(m.energy, periodic, rtol=1e-6)  # the trapezoid rule: sech tails are ~0 at the edges


@pytest.mark.parametrize("mode", [1, 5, -17])  # off the bin edges (multiples of 0.25)
def test_a_line_lands_in_the_bin_of_its_frequency_spread_by_the_response(mode):
    dw = 2 * math.pi / P.T
    w0 = mode * dw
    u, v = _line(w0)
    narrow = Instruments(spectrum_span=12.0, spectrum_bins=48, spectrum_resolution=1e-3, **QUIET)
    S = measure(u, v, P, narrow).spectrum[0]
    edges = torch.linspace(-6, 6, 49, dtype=torch.float64)
    j = int(torch.searchsorted(edges, torch.tensor(w0)) - 1)
    assert S[j] / S.sum() > 0.999
    # a Gaussian response of FWHM R puts erf-shares of the line into the bins around it
    R = 0.8
    wide = measure(u, v, P, Instruments(spectrum_span=12.0, spectrum_bins=48, spectrum_resolution=R, **QUIET)).spectrum[0]
    sigma = R / (2 * math.sqrt(2 * math.log(2)))
    cdf = 0.5 * (1 + torch.erf((edges - w0) / (sigma * math.sqrt(2))))
    expected = (cdf[1:] - cdf[:-1]) * S.sum()
    assert torch.allclose(wide, expected, atol=2e-3 * float(S.sum()))


def test_autocorrelation_of_a_gaussian_pulse():
    # I = exp(-t^2 / w^2) has A(tau) = exp(-tau^2 / (2 w^2))
    width = 2.0
    t = P.time_grid()
    u = torch.exp(-t**2 / (2 * width**2)).to(torch.complex128)[None]
    ins = Instruments(autocorrelation_points=41, autocorrelation_span=20.0, **QUIET)
    A = measure(u, torch.zeros_like(u), P, ins).autocorrelation[0]
    tau = torch.linspace(-10, 10, 41, dtype=torch.float64)
    assert torch.allclose(A, torch.exp(-tau**2 / (2 * width**2)), atol=2e-3)  # linear interpolation between samples
    assert A.max() == pytest.approx(1.0, abs=1e-12)


def test_noise_is_seeded_and_centred_on_the_clean_reading():
    u, v = sech_fields(256, P, dtype=torch.complex128)
    clean = measure(u, v, P, Instruments(**QUIET))
    noisy = [measure(u, v, P, Instruments(spectrum_floor=0.0), generator=torch.Generator().manual_seed(s)) for s in (1, 1, 2)]
    assert torch.equal(noisy[0].spectrum, noisy[1].spectrum) and not torch.equal(noisy[0].spectrum, noisy[2].spectrum)
    rel = noisy[2].energy / clean.energy - 1
    assert abs(float(rel.mean())) < 0.003 and float(rel.std()) == pytest.approx(0.01, rel=0.2)
    # readings of an empty bin: non-negative, of the floor's scale
    dark = measure(torch.zeros_like(u), torch.zeros_like(v), P, Instruments(), generator=torch.Generator().manual_seed(3))
    assert float(dark.spectrum.min()) >= 0 and float(dark.spectrum.mean()) == pytest.approx(1e-6 * math.sqrt(2 / math.pi), rel=0.05)


def test_measured_reward_prefers_a_pulse_to_a_line():
    pulse = sech_fields(1, P, amplitude=1.0, width=1.0, dtype=torch.complex128)
    line = _line(0.0, amplitude=float(torch.sqrt(torch.tensor(2.0 / 60.0))))  # same energy order
    for reward in ("autocorrelation", "spectrum"):
        ins = Instruments(reward=reward, **QUIET)
        assert measured_reward(measure(*pulse, P, ins), reward) > 5 * measured_reward(measure(*line, P, ins), reward)
    assert float(kurtosis(torch.ones(1, 8))) == math.inf


def test_measured_reward_ranks_settled_states_as_the_papers_r_does():
    from laserrl.analysis.measured import reward_agreement

    out = reward_agreement(states=64, seed=0, round_trips=100)
    ac, sp = out["rewards"]["autocorrelation"], out["rewards"]["spectrum"]
    assert out["locked"]["r>=0.15"] >= 2  # the draw has mode-locked states to tell apart
    assert ac["spearman"] > 0.9 and ac["auc_r>=0.15"] > 0.97
    assert ac["spearman"] > sp["spearman"] + 0.1  # the optical spectrum's kurtosis is the weaker stand-in
    # the level standing for r = 0.15 lies between the scores of plane waves and of pulses
    assert ac["median_r<0.02"] < ac["threshold_r>=0.15"] < ac["median_locked"]
    assert ac["threshold_r>=0.1"] <= ac["threshold_r>=0.15"]


def test_separating_threshold():
    import numpy as np

    from laserrl.analysis.measured import separating_threshold

    score = np.array([0.1, 0.2, 0.3, 0.6, 0.7, 0.25])
    assert separating_threshold(score, score >= 0.5) == pytest.approx(0.45)
    assert separating_threshold(score, np.array([0, 0, 1, 1, 1, 0], bool)) == pytest.approx(0.275)
    assert separating_threshold(score, np.zeros(6, bool)) is None


@pytest.mark.parametrize("settings, message", [
    ({"spectrum_bins": 2}, "spectrum_bins must be an integer >= 4"),
    ({"spectrum_bins": 7.5}, "spectrum_bins must be an integer"),
    ({"spectrum_span": 0}, "spectrum_span must be > 0"),
    ({"spectrum_resolution": -1.0}, "spectrum_resolution must be > 0"),
    ({"spectrum_noise": -0.1}, "spectrum_noise must be >= 0"),
    ({"energy_noise": float("nan")}, "energy_noise must be a finite number"),
    ({"autocorrelation_points": 2}, "autocorrelation_points must be 0"),
    ({"autocorrelation_points": 0}, "needs the autocorrelator"),
    ({"reward": "kurtosis"}, "reward must be 'autocorrelation' or 'spectrum'"),
    ({"spectrum_floor": "1e-6"}, "spectrum_floor must be a finite number"),
])
def test_bad_settings_name_the_setting(settings, message):
    with pytest.raises(ValueError, match=message):
        Instruments(**settings)


def test_settings_must_fit_the_grid():
    with pytest.raises(ValueError, match=r"spectrum_span \(30\) must be <= the grid's band"):
        Instruments(spectrum_span=30.0).check_grid(P)
    with pytest.raises(ValueError, match=r"autocorrelation_span \(80\) must be <= the window T = 60"):
        Instruments(autocorrelation_span=80.0).check_grid(P)
    assert spectrum_matrix(P, Instruments()).shape == (64, P.n)
