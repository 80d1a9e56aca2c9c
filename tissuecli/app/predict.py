"""The ``predict`` service: a fitted tissue's force for another session or recording,
with its 95 % predictive band, written as CSV."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from ..formats.csvfile import write_table
from ..formats.outputs import Output, check_outputs
from ..formats.params import read_fitted
from ..identify.predict import Prediction, predict_band
from .transfer import load_session


def predict_file(
    params: str | os.PathLike[str],
    data: str | os.PathLike[str],
    *,
    out: str | os.PathLike[str],
    session: str | None = None,
    force: bool = False,
    reading: dict[str, Any] | None = None,
    filtered: bool = False,
) -> Prediction:
    """Predict the force of ``data`` (a session of a tissuecli HDF5 file, or any
    recording ``import`` reads) with the tissue of ``params`` (a ``fit --out`` file) and
    write ``time,force_pred,force_lo,force_hi,force`` (s, N) to ``out``, one row per
    sample of ``data``.

    ``force_pred`` is the law applied to the best estimate of each sample's kinematics
    and ``force`` the force as measured; with ``filtered``, both are filtered as in a
    fit. Samples that cannot be predicted (inside a gap in the stamps; with
    ``filtered``, at the filter's edges) are NaN. The band carries the coefficients'
    covariance and the noise when the parameter file holds them (every file ``fit``
    writes does).
    """
    check_outputs([Output(out, "--out")], [params, data], force=force)
    tissue, cov, noise_sd = read_fitted(params)
    recording, _ = load_session(data, session, **(reading or {}))
    pred = predict_band(tissue, recording, cov=cov, noise_sd=noise_sd, filtered=filtered)
    what = (
        "forces filtered as in a fit"
        if filtered
        else "force as measured, force_pred the law on Savitzky-Golay kinematics"
    )
    write_table(
        out,
        ["time", "force_pred", "force_lo", "force_hi", "force"],
        np.column_stack([pred.time, pred.predicted, pred.lower, pred.upper, pred.force]),
        comment=f"tissuecli predict: law {tissue.law.name}; time in s, forces in N ({what}; "
        "nan where a sample cannot be predicted); force_lo and force_hi bound the 95 % "
        "predictive band",
    )
    return pred
