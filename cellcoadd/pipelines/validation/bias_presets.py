"""Per-row settings of the shear-bias table (``benchmarks/shear_bias.py``): presets.

A row of the paper's Table 1 is a method and a mode (``"metacal-coadd"``,
``"bfd-multi-epoch"``, ...). :func:`row_settings` turns a row and a preset into the
keyword arguments of :func:`~cellcoadd.pipelines.validate_shear`:

``"none"``
    What the command line gives, the same for every row (S/N, input shear, ring partners).
``"high-snr"``
    S/N 10^4 with what each row needs there (docs/validation.md, "BFD at S/N 10^4"):

    * metacal and AnaCal: ``g1 = 0.02`` (the paper's), ring partners (the mean intrinsic
      shape cancels in ``c``);
    * BFD: the targets themselves, unsheared, as the templates (no template of an
      independent sample overlaps a target's ~1e-4-wide likelihood), hence no ring
      partners (a partner would be a second template within the noise of a near-round
      target), a small input shear ``g1 = 1e-3`` (no third-order terms) and the default
      k-space oversampling
      (:data:`~cellcoadd.pipelines.validation.validation_settings.BFD_OVERSAMPLE`).

    :data:`HIGH_SNR_PAIRS` gives each row enough pairs for ``sigma_m <= 2e-4`` (about
    1e-4 expected from the per-pair scatter measured on smaller runs), about 20 CPU
    minutes for the five rows of Table 1.
"""

from __future__ import annotations

from typing import Any

from cellcoadd.errors import ConfigError
from cellcoadd.pipelines.validation.validation_settings import BFD_OVERSAMPLE, check_method_mode

#: Presets of :func:`row_settings`.
PRESETS: tuple[str, ...] = ("none", "high-snr")
#: S/N of the ``high-snr`` preset.
HIGH_SNR = 1.0e4
#: Input shear of the ``high-snr`` BFD rows (the metacal and AnaCal rows keep 0.02).
BFD_HIGH_SNR_SHEAR = 1.0e-3
#: Default input shear g1 (the paper's).
DEFAULT_SHEAR = 0.02
#: Pairs per row of the ``high-snr`` preset: sigma_m ~ 1e-4 expected from the per-pair
#: scatter of m at S/N 10^4 (metacal ~1.8e-3, BFD up to ~2.8e-3 at g1 = 1e-3 with rare
#: outliers, AnaCal ~1.1e-3; docs/validation.md), half the 2e-4 aimed at.
HIGH_SNR_PAIRS: dict[str, int] = {
    "metacal-coadd": 300,
    "metacal-multi-epoch": 250,
    "metacal-single": 300,
    "bfd-coadd": 200,
    "bfd-multi-epoch": 100,
    "bfd-single": 100,
    "anacal-coadd": 150,
    "anacal-single": 150,
}


def split_row(row: str) -> tuple[str, str]:
    """``"bfd-multi-epoch"`` -> ``("bfd", "multi-epoch")``, checked.

    Raises
    ------
    ConfigError
        An unknown method or mode, or a method that does not run in that mode.
    """
    method, _, mode = row.partition("-")
    check_method_mode(method, mode)
    return method, mode


def row_settings(
    row: str,
    preset: str = "none",
    *,
    snr: float | tuple[float, float] | None = (10.0, 50.0),
    shear: float | None = None,
    rotated_partners: bool = True,
    shape: str = "admom",
) -> dict[str, Any]:
    """Keyword arguments of :func:`~cellcoadd.pipelines.validate_shear` for one row.

    Parameters
    ----------
    row : str
        ``"<method>-<mode>"``, e.g. ``"metacal-coadd"``.
    preset : {"none", "high-snr"}
        See the module docstring; ``"high-snr"`` overrides ``snr`` and
        ``rotated_partners``, and ``shear`` unless it is given.
    snr : float or (float, float) or None
        Target S/N of the ``"none"`` preset.
    shear : float, optional
        Input shear g1; default 0.02 (``"high-snr"`` BFD rows: 1e-3).
    rotated_partners : bool
        Ring partners (``"none"`` preset).
    shape : {"admom", "wmom"}
        Metacal shape (other methods ignore it).

    Returns
    -------
    dict
        ``mode``, ``method``, ``snr``, ``shear`` (the input g1), ``shape``,
        ``rotated_partners`` and, for BFD, ``bfd_template_sample`` and ``bfd_oversample``.

    Raises
    ------
    ConfigError
        An unknown row or preset, or a zero input shear.
    """
    method, mode = split_row(row)
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; known: {PRESETS}")
    template_sample = "independent"
    if preset == "high-snr":
        snr = HIGH_SNR
        targets = method == "bfd"
        template_sample = "targets" if targets else "independent"
        rotated_partners = not targets
        if shear is None:
            shear = BFD_HIGH_SNR_SHEAR if targets else DEFAULT_SHEAR
    g1 = DEFAULT_SHEAR if shear is None else float(shear)
    if g1 == 0.0:
        raise ConfigError("the input shear g1 must not be 0")
    options: dict[str, Any] = {
        "mode": mode,
        "method": method,
        "snr": snr,
        "shear": g1,
        "shape": shape if method == "metacal" else "admom",
        "rotated_partners": rotated_partners,
    }
    if method == "bfd":
        options["bfd_template_sample"] = template_sample
        options["bfd_oversample"] = BFD_OVERSAMPLE
    return options


def describe_settings(options: dict[str, Any]) -> str:
    """One line saying what a row ran with (S/N, g1, partners, templates, ...)."""
    snr = options["snr"]
    if snr is None:
        snr_text = "sim noise"
    elif isinstance(snr, tuple):
        snr_text = f"S/N {snr[0]:g}-{snr[1]:g}"
    else:
        snr_text = f"S/N {snr:g}"
    parts = [snr_text, f"g1 = {options['shear']:g}"]
    parts.append("ring partners" if options["rotated_partners"] else "no ring partners")
    if options["method"] == "metacal":
        parts.append(f"shape {options['shape']}")
    if options["method"] == "bfd":
        if options["bfd_template_sample"] == "targets":
            parts.append("templates: the targets unsheared (1 rotation)")
        else:
            parts.append(f"{options.get('bfd_templates', 100)} independent templates x 8 rotations")
        parts.append(f"oversample {options['bfd_oversample']}")
    return ", ".join(parts)


__all__ = [
    "BFD_HIGH_SNR_SHEAR",
    "DEFAULT_SHEAR",
    "HIGH_SNR",
    "HIGH_SNR_PAIRS",
    "PRESETS",
    "describe_settings",
    "row_settings",
    "split_row",
]
