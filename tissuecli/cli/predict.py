"""``tissuecli predict``: a fitted tissue's force for another grasp, with its band."""

from __future__ import annotations

import click

from .base import cli
from .options import file_argument, force_option, reading, recording_options, session_option


@cli.command()
@file_argument("params")
@file_argument("data")
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False),
    help="CSV to write: time,force_pred,force_lo,force_hi,force (s, N), a row per sample.",
)
@click.option(
    "--filtered",
    is_flag=True,
    help="Predict the force filtered as in a fit, and filter the measured force alike "
    "[default: the force itself, against the force as measured].",
)
@session_option("Session of DATA to predict [default: the only one].")
@recording_options()
@force_option()
def predict(
    params: str,
    data: str,
    out: str,
    filtered: bool,
    session: str | None,
    columns: str | None,
    units: str | None,
    jaw_length: str | None,
    rate: float | None,
    sheet: str | None,
    force: bool,
) -> None:
    """Predict the force of a session with a fitted tissue, with its 95 % predictive
    band: validate a law on a grasp it was not fitted to.

    PARAMS is a parameter file from `fit --out`; DATA a session of a tissuecli HDF5
    file or any recording `import` reads. One row per sample of DATA: the law applied
    to the best estimate of that sample's closure, speed and acceleration
    (Savitzky-Golay), beside the force as measured; nan where a sample cannot be
    predicted (inside a gap). A law with memory (relaxation) starts from rest at
    DATA's first sample.

    \b
    Examples:
        tissuecli predict liver.json grasp.h5 --session liver-2 --out pred.csv
        tissuecli predict rig.json data/davinci_instrument_L4_45_first10s.TXT --out pred.csv \\
            --columns time=1,force=3,position=2 --jaw-length 10mm \\
            --units "time=s,force=3.9811e-5*Nm,position=0.00076699*rad"
    """
    from ..app.predict import predict_file

    pred = predict_file(
        params,
        data,
        out=out,
        session=session,
        force=force,
        reading=reading(columns, units, jaw_length, rate, sheet),
        filtered=filtered,
    )
    what = "filtered force" if filtered else "force"
    click.echo(
        f"predicted {pred.count} of {pred.time.size} samples: error {pred.rms_n:.4g} N RMS "
        f"against a {what} SD of {pred.force_sd_n:.4g} N (R^2 {pred.r2:.3f}); "
        f"{100 * pred.inside:.1f} % of the measured {what} inside the 95 % band"
    )
    click.echo(f"prediction written to {out}")
