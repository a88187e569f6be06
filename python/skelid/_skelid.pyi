"""Type hints of skelid's compiled module (see each function's docstring)."""

from os import PathLike
from typing import Any, Literal, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

__version__: str

Samples = Union[npt.NDArray[np.float64], npt.NDArray[np.float32], Sequence[float]]
Backend = Literal["auto", "cpu", "gpu"]
Kind = Literal["base_motion", "force", "free"]

class SkelidError(Exception):
    """An error reported by skelid, with the library's message."""

def track(
    x: Samples,
    fs: float,
    method: Literal["wavelet", "hilbert"] = "wavelet",
    fmin: Optional[float] = None,
    fmax: Optional[float] = None,
    scales: Optional[int] = None,
    bandwidth: Optional[float] = None,
    cutoff: Optional[float] = 0.005,
    backend: Backend = "auto",
) -> dict[str, Any]:
    """Envelope, frequency and phase of one signal: time, amplitude, frequency, phase,
    valid (numpy arrays), band, noise, offset, backend, method."""

def identify(
    input: Optional[Samples],
    output: Samples,
    fs: float,
    kind: Kind = "base_motion",
    method: Literal["wavelet", "hilbert"] = "wavelet",
    inertia: Optional[float] = None,
    gravity_stiffness: float = 0.0,
    input_quantity: Optional[str] = None,
    output_quantity: Optional[str] = None,
    units: Optional[str] = None,
    mode_band: Optional[Tuple[float, float]] = None,
    mode_near: Optional[float] = None,
    fmin: Optional[float] = None,
    fmax: Optional[float] = None,
    scales: Optional[int] = None,
    bandwidth: Optional[float] = None,
    bins: int = 40,
    resonance: float = 0.1,
    cutoff: Optional[float] = 0.005,
    backend: Backend = "auto",
) -> dict[str, Any]:
    """The joint of one run: parameters (with `_stderr`), units, skeleton arrays,
    response and input tracks, valid, mode_band, warnings."""

def gap(
    model: Union[str, "PathLike[str]", Mapping[str, Any]],
    input: Samples,
    output: Samples,
    fs: float,
    kind: Literal["base_motion"] = "base_motion",
    inertia: Optional[float] = None,
    gravity_stiffness: float = 0.0,
    units: Optional[str] = None,
    holdout_block: float = 1.0,
    baseline_evaluations: int = 150,
    candidate_evaluations: int = 45,
    pairs: bool = True,
    fit_inertia: bool = False,
    effects: Optional[Sequence[str]] = None,
    backend: Backend = "cpu",
    waveform: bool = True,
    zero_tolerance: Optional[float] = None,
    refit_effects: bool = False,
) -> dict[str, Any]:
    """The gap.json document: format, settings, runs (one entry: nominal_gap,
    baseline_gap, regions, candidates, verdict), failed."""

def read_campaign(
    path: Union[str, "PathLike[str]"],
    sample_rate: Optional[float] = None,
    input_name: str = "input",
    output_name: str = "output",
    runs: Optional[str] = None,
    kind: Optional[Kind] = None,
    errors: Literal["raise", "keep"] = "raise",
) -> list[dict[str, Any]]:
    """The runs of a campaign archive as dicts of numpy arrays and metadata."""
