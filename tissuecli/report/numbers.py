"""Numbers for people: significant digits an uncertainty supports, powers of ten without
overflow, probabilities, Jeffreys' words, units. Everything returns HTML markup."""

from __future__ import annotations

import html
import math

from ..identify.bayes import DECISIVE

#: SI unit -> (convenient unit, factor from SI) for the convenience columns.
CONVENIENT: dict[str, tuple[str, float]] = {
    "N/m": ("N/mm", 1e-3),
    "N/m^3": ("N/mm³", 1e-9),
    "N s/m": ("N s/mm", 1e-3),
    "N s^2/m^2": ("N s²/mm²", 1e-6),
    "kg": ("g", 1e3),
}


def esc(text: object) -> str:
    """HTML-escaped text."""
    return html.escape(str(text), quote=True)


def is_finite(v: float | None) -> bool:
    return v is not None and math.isfinite(v)


def sig(v: float | None, digits: int = 4) -> str:
    """``v`` to ``digits`` significant digits as markup; scientific outside 1e-3 .. 1e5."""
    if v is None:
        return "—"
    if not math.isfinite(v):
        return esc(str(v))
    if v == 0:
        return "0"
    digits = max(1, digits)
    exp = math.floor(math.log10(abs(v)))
    if -3 <= exp < 5 and not (exp >= 4 and exp >= digits):
        v = round(v, digits - 1 - exp) if exp >= digits else v
        text = f"{v:.{max(digits - 1 - exp, 0)}f}"
        if float(text) != 0 and math.floor(math.log10(abs(float(text)))) > exp:
            text = f"{v:.{max(digits - 2 - exp, 0)}f}"  # rounding carried a digit (9.99 -> 10.0)
        return text.replace("-", "−")
    mant, power = f"{v:.{digits - 1}e}".split("e")
    return f"{mant.replace('-', '−')}&#8239;×&#8239;10<sup>{int(power)}</sup>".replace(
        "<sup>-", "<sup>−"
    )


def fixed(v: float, decimals: int = 2, sign: bool = False) -> str:
    """``v`` with a fixed number of decimals and a true minus sign."""
    if not math.isfinite(v):
        return esc(str(v))
    return (f"{v:+.{decimals}f}" if sign else f"{v:.{decimals}f}").replace("-", "−")


def at_place(v: float, place: int) -> str:
    """``v`` rounded to the decimal place ``10**place``."""
    if not math.isfinite(v) or v == 0:
        return sig(v)
    return sig(v, min(max(math.floor(math.log10(abs(v))) - place + 1, 1), 9))


def place(sd: float) -> int:
    """Decimal place of the second significant digit of an uncertainty."""
    return math.floor(math.log10(sd)) - 1 if is_finite(sd) and sd > 0 else -12


def with_sd(mean: float, sd: float) -> str:
    """A mean with the digits its SD supports (two significant digits of the SD)."""
    if not (is_finite(sd) and sd > 0):
        return sig(mean, 6)
    return at_place(mean, place(sd))


def power_of_ten(ln_value: float) -> str:
    """``exp(ln_value)`` as markup, without overflow for huge or tiny values."""
    if not math.isfinite(ln_value):
        return "0" if ln_value < 0 else "∞"
    if abs(ln_value) < math.log(1e5):
        return sig(math.exp(ln_value), 3)
    p10 = ln_value / math.log(10)
    exp = math.floor(p10)
    mant = 10 ** (p10 - exp)
    if round(mant, 1) >= 10:
        mant, exp = 1.0, exp + 1
    return f"{mant:.1f}&#8239;×&#8239;10<sup>{exp}</sup>".replace("<sup>-", "<sup>−")


def probability(ln_p: float) -> str:
    """A probability given its logarithm: three decimals, or a power of ten when tiny."""
    p = math.exp(ln_p)
    if p >= 1e-3:
        return f"{p:.3f}"
    return "≈ " + power_of_ten(ln_p)


def jeffreys(ln_bf: float) -> str:
    """Jeffreys' words for the evidence against a form, from its ln Bayes factor."""
    if ln_bf <= 0:
        return "best"
    for limit, word in (
        (math.log(10**0.5), "barely worth mentioning"),
        (math.log(10.0), "substantial"),
        (DECISIVE, "strong"),
    ):
        if ln_bf < limit:
            return word
    return "decisive"


def unit_html(unit: str) -> str:
    """A unit for display: N/m^3 -> N/m³."""
    return unit.replace("^2", "²").replace("^3", "³")


def unit_tex(unit: str) -> str:
    """A unit for matplotlib mathtext."""
    return unit.replace("^2", "$^2$").replace("^3", "$^3$")


def convenient(value: float, unit: str) -> tuple[str, float] | None:
    if unit not in CONVENIENT:
        return None
    name, factor = CONVENIENT[unit]
    return name, value * factor
