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

    Coadd rows put each object at a random position within :data:`TABLE_OBJECT_OFFSET`
    coadd pixels of its cell's centre and measure it with the PSF ``psf_at`` serves there
    (``object_offset``), where the served PSF can err, instead of on the centre pixel.

    :data:`HIGH_SNR_PAIRS` gives each row enough pairs for ``sigma_m <= 2e-4`` (about
    1e-4 expected from the per-pair scatter measured on smaller runs), about 20 CPU
    minutes for the five rows of Table 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

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
#: ``object_offset`` of the ``high-snr`` coadd rows, coadd pixels: every sub-pixel phase
#: of the coadd grid and ~2.5 periods of the inputs' resampling pattern (0.27" epochs on
#: 0.2" coadd pixels repeat every ~3.9 coadd pixels), the galaxy >= 20 px from the edge.
TABLE_OBJECT_OFFSET = 5.0
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


#: Highest S/N at which BFD's independent templates cover the targets (the paper selects
#: 5 < S/N < 50; above it no flux selection applies and the targets serve as templates).
BFD_INDEPENDENT_MAX_SNR = 50.0
#: Independent BFD templates when none are asked for: at S/N 10-50, 100 templates gave
#: m1 = +0.20 +- 0.07 (the prior's sampling noise), 400 +0.10 +- 0.05, 1600 +0.008 +-
#: 0.017, the precision the forecast table states (docs/validation.md).
BFD_DEFAULT_TEMPLATES = 1600


@dataclass(frozen=True)
class BfdChoice:
    """BFD settings of a run, chosen from its S/N where not given (:func:`choose_bfd`).

    Attributes
    ----------
    template_sample : {"independent", "targets"}
        Where the templates come from.
    templates : int
        Independent templates (ignored with ``"targets"``).
    rotated_partners : bool
        Ring partners.
    shear : float or None
        Input g1 (None: the default 0.02).
    note : str
        What was chosen and why, or a warning about an explicit choice ("" when nothing).
    """

    template_sample: Literal["independent", "targets"]
    templates: int
    rotated_partners: bool
    shear: float | None
    note: str


def choose_bfd(
    snr: float | tuple[float, float] | None,
    *,
    template_sample: Literal["independent", "targets"] | None = None,
    templates: int | None = None,
    rotated_partners: bool | None = None,
    shear: float | None = None,
) -> BfdChoice:
    """The BFD settings for target S/N ``snr``; each argument left None is chosen from it.

    * S/N above :data:`BFD_INDEPENDENT_MAX_SNR` (the default 10^4 of ``validate-shear``):
      no independent sample covers a near-noiseless target's ~1e-4-wide likelihood (100
      templates gave ``m1 = -0.40``), so the targets themselves, unsheared, are the
      templates, without ring partners, at ``g1 = 1e-3`` (the ``high-snr`` preset's BFD
      rows). Independent templates asked for there are refused.
    * S/N up to 50 (or the paper's noise): :data:`BFD_DEFAULT_TEMPLATES` independent
      templates, ring partners; fewer asked for are run with a warning in ``note``.
    * A range across 50 is refused (neither prior serves all of it).

    Raises
    ------
    ConfigError
        A combination that gives a wrong ``m1``; the message names the flags of
        ``validate-shear`` that fix it.
    """
    lo, hi = (None, None) if snr is None else (snr, snr) if isinstance(snr, float | int) else snr
    limit = BFD_INDEPENDENT_MAX_SNR
    if lo is not None and hi is not None and lo <= limit < hi and template_sample != "targets":
        raise ConfigError(
            f"BFD: the S/N range {lo:g}-{hi:g} straddles {limit:g}: independent templates "
            f"cover targets up to S/N {limit:g} only, the targets as templates serve near-"
            f"noiseless ones; give --snr within 10-{limit:g} (e.g. --snr 10,50) or above it "
            "(e.g. --snr 10000)",
            value=snr,
        )
    if lo is not None and lo > limit:
        if template_sample == "independent" or (template_sample is None and templates):
            raise ConfigError(
                f"BFD at S/N {lo:g} > {limit:g} cannot use independent templates (an "
                "independent sample of any practical size cannot cover near-noiseless "
                "targets: 100 templates gave m1 = -0.40 at S/N 10^4); leave out "
                "--bfd-template-sample independent and --bfd-templates (the default at this "
                "S/N is --bfd-template-sample targets --no-rotated-partners --shear 0.001), "
                f"or lower the S/N (--snr 10,{limit:g})",
                value=template_sample,
            )
        chosen = template_sample is None or rotated_partners is None or shear is None
        return BfdChoice(
            template_sample="targets",
            templates=templates or 100,  # not used: the targets are the templates
            rotated_partners=False if rotated_partners is None else rotated_partners,
            shear=BFD_HIGH_SNR_SHEAR if shear is None else shear,
            note=(
                f"BFD at S/N {lo:g}: the targets themselves as templates, no ring partners, "
                f"g1 = {BFD_HIGH_SNR_SHEAR:g} (as --bfd-template-sample targets "
                "--no-rotated-partners --shear 0.001)"
                if chosen
                else ""
            ),
        )
    sample = template_sample or "independent"
    count = BFD_DEFAULT_TEMPLATES if templates is None else templates
    note = ""
    if sample == "independent" and count < BFD_DEFAULT_TEMPLATES:
        note = (
            f"warning: {count} BFD templates sample the prior too sparsely at S/N 10-50 "
            f"(100 gave m1 = +0.20 +- 0.07); the default {BFD_DEFAULT_TEMPLATES} is "
            "consistent with zero"
        )
    return BfdChoice(
        template_sample=sample,
        templates=count,
        rotated_partners=True if rotated_partners is None else rotated_partners,
        shear=shear,
        note=note,
    )


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
    object_offset: float | None = None,
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
    object_offset : float, optional
        Coadd rows: random object positions within this many coadd pixels of the cell
        centre (default: :data:`TABLE_OBJECT_OFFSET` with ``"high-snr"``, else 0).

    Returns
    -------
    dict
        ``mode``, ``method``, ``snr``, ``shear`` (the input g1), ``shape``,
        ``rotated_partners``, ``object_offset`` for coadd rows and, for BFD,
        ``bfd_template_sample`` and ``bfd_oversample``.

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
    if mode == "coadd":
        if object_offset is None:
            object_offset = TABLE_OBJECT_OFFSET if preset == "high-snr" else 0.0
        options["object_offset"] = float(object_offset)
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
    if options.get("object_offset"):
        parts.append(f"objects within {options['object_offset']:g} px of the cell centre")
    if options["method"] == "bfd":
        if options["bfd_template_sample"] == "targets":
            parts.append("templates: the targets unsheared (1 rotation)")
        else:
            parts.append(
                f"{options.get('bfd_templates', BFD_DEFAULT_TEMPLATES)} independent templates "
                "x 8 rotations"
            )
        parts.append(f"oversample {options['bfd_oversample']}")
    return ", ".join(parts)


__all__ = [
    "BFD_DEFAULT_TEMPLATES",
    "BFD_HIGH_SNR_SHEAR",
    "BFD_INDEPENDENT_MAX_SNR",
    "BfdChoice",
    "DEFAULT_SHEAR",
    "HIGH_SNR",
    "HIGH_SNR_PAIRS",
    "TABLE_OBJECT_OFFSET",
    "PRESETS",
    "choose_bfd",
    "describe_settings",
    "row_settings",
    "split_row",
]
