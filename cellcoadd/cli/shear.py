"""``cellcoadd validate-shear``: metacal or BFD shear bias on the paper's stamp simulations."""

from __future__ import annotations

import json
import math

import click

from cellcoadd.cli.options import quiet_option
from cellcoadd.pipelines.validation.bias_precision import (
    REFERENCE_SHEAR,
    SNR_CUT,
    TARGET_M_ERR,
    ForecastRow,
    error_scales,
    forecast,
    forecast_scale,
    pairs_needed,
)

#: default --snr: high S/N isolates the coadd's own bias (its error on m1 is smallest:
#: :mod:`cellcoadd.pipelines.validation.bias_precision`)
DEFAULT_SNR = "10000"
#: default --n-objects: about a minute of CPU, m1 to about +-2e-4 at the default S/N
DEFAULT_N_OBJECTS = 100
#: default --bfd-oversample: ValidationSettings.bfd_oversample (a test checks they agree;
#: importing the settings here would load the builder for every command line)
BFD_OVERSAMPLE = 4
#: default --shear: the paper's g1
DEFAULT_SHEAR = 0.02


def parse_snr(text: str | None) -> float | tuple[float, float] | None:
    """``"30"`` -> 30.0, ``"10,50"`` -> (10.0, 50.0), None or ``"paper"`` -> None."""
    if text is None or text.strip().lower() == "paper":
        return None
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        raise click.BadParameter(f"expected VALUE or LO,HI, got {text!r}") from None
    if len(values) not in (1, 2) or not all(math.isfinite(v) and v > 0 for v in values):
        raise click.BadParameter(f"expected one or two positive numbers, got {text!r}")
    if len(values) == 2 and values[0] > values[1]:
        raise click.BadParameter(f"LO must not exceed HI, got {text!r}")
    return values[0] if len(values) == 1 else (values[0], values[1])


def _finite_or_null(value: object) -> object:
    """NaN and infinities become null, so the output is strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _finite_or_null(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_null(item) for item in value]
    return value


@click.command("validate-shear")
@click.option(
    "--method",
    type=click.Choice(["metacal", "bfd", "anacal"]),
    default="metacal",
    show_default=True,
    help="Shear method: metacalibration, BFD (Bayesian Fourier Domain) or AnaCal's FPFS "
    "(coadd or single mode; needs the optional extra cellcoadd[anacal]).",
)
@click.option(
    "--mode",
    type=click.Choice(["coadd", "single", "multi-epoch"]),
    default="coadd",
    show_default=True,
    help="coadd: measure the cell coadd of 10 epochs; multi-epoch: the 10 epochs jointly in "
    "their own pixels (metacal: one joint shape; BFD: summed moments); single: the first "
    "epoch alone.",
)
@click.option(
    "--shape",
    type=click.Choice(["admom", "wmom"]),
    default="admom",
    show_default=True,
    help="Metacal shape: adaptive moments, or moments in a fixed Gaussian weight.",
)
@click.option(
    "--wmom-fwhm",
    type=click.FloatRange(min=0.0, min_open=True),
    default=1.2,
    show_default=True,
    help="FWHM (arcsec) of the fixed weight of --shape wmom.",
)
@click.option(
    "--no-rotated-partners",
    "unrotated",
    is_flag=True,
    help="Do not pair objects 2k, 2k+1 as 90-degree-rotated partners (c then includes the "
    "sample's mean intrinsic shape).",
)
@click.option(
    "--bfd-templates",
    type=click.IntRange(min=1),
    default=None,
    help="Independent deep templates of the BFD prior (--method bfd). Default: 1600 at "
    "S/N up to 50 (fewer leave m1 biased: 100 gave +0.20); refused above S/N 50.",
)
@click.option(
    "--bfd-template-sample",
    type=click.Choice(["independent", "targets"]),
    default=None,
    help="BFD templates from an independent sample, or the targets themselves unsheared. "
    "Default from --snr: the targets above S/N 50 (with no ring partners and --shear "
    "0.001 unless given), independent ones up to 50.",
)
@click.option(
    "--bfd-oversample",
    type=click.IntRange(min=1, max=8),
    default=BFD_OVERSAMPLE,
    show_default=True,
    help="k-space oversampling (zero padding) of the BFD moments: below 4 the shear "
    "derivatives of small galaxies are inaccurate (1: m1 off by a few per cent).",
)
@click.option(
    "--bfd-mirror",
    is_flag=True,
    help="Add each template copy's mirror image to the BFD prior (twice the cost of P, Q, "
    "R; no measurable change on the simulated population, see docs/validation.md).",
)
@click.option(
    "--shear",
    "shear",
    type=click.FloatRange(min=-0.5, max=0.5),
    default=DEFAULT_SHEAR,
    show_default=True,
    metavar="G",
    help="Input shear g1 of the +g/-g pairs (g2 = 0); m1 is measured against it. BFD's "
    "high-S/N check needs a small one (1e-3: no third-order terms).",
)
@click.option(
    "--n-objects",
    type=click.IntRange(min=2),
    default=DEFAULT_N_OBJECTS,
    show_default=True,
    help="Objects, each simulated as a +g/-g pair; the error on m1 falls as 1/sqrt(N).",
)
@click.option(
    "--snr",
    "snr_text",
    metavar="VALUE|LO,HI|paper",
    default=DEFAULT_SNR,
    show_default=True,
    help="Target S/N, VALUE or a range LO,HI drawn per object, or 'paper' for the paper's "
    "DES-like noise (needs ~10^5 objects for a useful m1).",
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option(
    "--workers", type=click.IntRange(min=1), default=1, show_default=True, help="Local processes."
)
@click.option("--scheduler", help="dask.distributed scheduler address (runs objects there).")
@click.option(
    "--coadd-pixel-scale",
    type=click.FloatRange(min=0.0, min_open=True),
    default=0.2,
    show_default=True,
    help="Coadd pixel scale, arcsec (0.27: the exposures' scale).",
)
@click.option(
    "--object-offset",
    type=click.FloatRange(min=0.0, max=100.0),
    default=0.0,
    show_default=True,
    metavar="PX",
    help="Coadd mode: put each object at a random position within PX coadd pixels of its "
    "cell's centre (each axis) and measure it with the PSF cell.psf_at serves there (0: on "
    "the centre pixel, where cell.psf was drawn). Table 1's coadd rows use 5.",
)
@click.option(
    "--checkpoint",
    type=click.Path(dir_okay=False),
    help="Save the measured pairs here every --checkpoint-every pairs; an existing file of "
    "the same settings is resumed (a killed run loses and repeats no pair).",
)
@click.option(
    "--checkpoint-every",
    type=click.IntRange(min=1),
    default=1000,
    show_default=True,
    help="Pairs between checkpoints.",
)
@click.option(
    "--target-sigma",
    type=click.FloatRange(min=0.0, min_open=True),
    default=4e-4,
    show_default=True,
    help="Print the pairs and CPU hours this sigma(m1) would take (the paper's: 4e-4).",
)
@click.option(
    "--compare-cuts",
    is_flag=True,
    help="Metacal: also m1 without cuts, with each cut alone and with both, and each one's "
    "paired difference from no cuts (whether a cut biases m1, and what it costs).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a table.")
@quiet_option
@click.pass_context
def validate_shear(
    ctx: click.Context,
    method: str,
    mode: str,
    shape: str,
    wmom_fwhm: float,
    unrotated: bool,
    bfd_templates: int | None,
    bfd_template_sample: str | None,
    bfd_oversample: int,
    bfd_mirror: bool,
    shear: float,
    n_objects: int,
    snr_text: str | None,
    seed: int,
    workers: int,
    scheduler: str | None,
    coadd_pixel_scale: float,
    object_offset: float,
    checkpoint: str | None,
    checkpoint_every: int,
    target_sigma: float,
    compare_cuts: bool,
    as_json: bool,
    quiet: bool,
) -> None:
    """Measure the shear bias m, c of metacalibration, BFD or AnaCal on cell coadds (paper Table 1).

    Simulates isolated exponential galaxies in 10 epochs (paper section 3) as +g/-g
    pairs with g1 = 0.02 (--shear; objects 2k+1 are 90-degree-rotated partners of objects 2k),
    coadds each object's epochs into one cell with the cellcoadd builder, runs
    metacalibration with the cell's noise realization (or BFD: moments with the
    covariance from the noise realization and a template prior) and prints m1, c1,
    c2 (jackknife errors, ring partners kept together), the objects used after the paper's
    cuts and the CPU time, beside the paper's value. The multi-epoch mode is the paper's
    reference: metacal on each epoch (own PSF, one common reconvolution PSF, own noise
    correction) with one joint shape, or BFD moments summed over the epochs (metacal:
    about 4 times the CPU of coadd mode per pair). The defaults (100 pairs at S/N 10000,
    about a minute of CPU) measure the coadd's own bias to about +-2.6e-4.

    Before the run it prints the error to expect from a stored table of measured
    sigma(m1) x sqrt(N) per method, mode and S/N (at S/N 10000: metacal 2.6e-3 on coadds,
    1.9e-3 multi-epoch, AnaCal 1.5e-3, BFD 2.3e-3 on coadds and 9.6e-3 multi-epoch at
    g1 = 0.001; at S/N 10-50: metacal admom 1.7, wmom 0.9, BFD 0.40; at the paper's noise
    ~100; docs/validation.md); after it, the pairs that would reach +-3e-4 and the pairs
    and CPU hours of --target-sigma (from the table where it has the row).

    \b
    Examples:
      cellcoadd validate-shear
      cellcoadd validate-shear --n-objects 40 --snr 10000
      cellcoadd validate-shear --mode multi-epoch --n-objects 16 --snr 10000
      cellcoadd validate-shear --mode single --n-objects 40 --snr 10000
      cellcoadd validate-shear --n-objects 2000 --snr 10,50 --workers 2
      cellcoadd validate-shear --n-objects 100000 --snr 10,50 --scheduler tcp://host:8786 \\
          --checkpoint run.npz --checkpoint-every 2000
      cellcoadd validate-shear --n-objects 20 --snr 1000 --json --quiet
      cellcoadd validate-shear --shape wmom --n-objects 400 --snr 10,50
      cellcoadd validate-shear --shape wmom --n-objects 400 --snr 10,50 --compare-cuts
      cellcoadd validate-shear --method bfd --n-objects 200 --snr 20
      cellcoadd validate-shear --method bfd --n-objects 16 --snr 10000 --shear 0.001 \\
          --bfd-template-sample targets --no-rotated-partners
      cellcoadd validate-shear --method anacal --n-objects 40 --snr 10000
      cellcoadd validate-shear --n-objects 300 --object-offset 5

    BFD's prior must overlap every target within its noise, so its settings follow
    --snr unless given: above S/N 50 (the default 10000) the targets themselves serve as
    templates, with no ring partners and --shear 0.001 (no third-order terms), and
    independent templates are refused; up to S/N 50 (the paper selects 5 < S/N < 50),
    1600 independent templates (100 left m1 biased by +0.20).
    """
    from cellcoadd.errors import ConfigError
    from cellcoadd.pipelines.validation.bias_table import format_bias_table, format_cut_comparison
    from cellcoadd.pipelines.validation.shear_validation import RESULT_KEYS
    from cellcoadd.pipelines.validation.shear_validation import validate_shear as run_validation
    from cellcoadd.pipelines.validation.validation_settings import check_method_mode

    try:
        check_method_mode(method, mode)
    except ConfigError as exc:
        raise click.UsageError(str(exc)) from None
    if method != "metacal" and shape != "admom":
        raise click.UsageError("--shape applies to --method metacal only")
    if method != "metacal" and compare_cuts:
        raise click.UsageError("--compare-cuts applies to --method metacal only")
    if method == "anacal":
        from cellcoadd.shear.anacal_adapter import require_anacal

        try:
            require_anacal()
        except ImportError as exc:
            raise click.ClickException(str(exc)) from exc
    if shear == 0.0:
        raise click.BadParameter("the input shear must not be 0", param_hint="--shear")
    rotated: bool | None = False if unrotated else None
    if method == "bfd":
        from cellcoadd.pipelines.validation.bias_presets import choose_bfd

        given = ctx.get_parameter_source("shear") not in _DEFAULT_SOURCES
        try:
            bfd = choose_bfd(
                parse_snr(snr_text),
                template_sample=bfd_template_sample,  # type: ignore[arg-type]
                templates=bfd_templates,
                rotated_partners=rotated,
                shear=shear if given else None,
            )
        except ConfigError as exc:
            raise click.UsageError(str(exc)) from None
        bfd_template_sample, bfd_templates = bfd.template_sample, bfd.templates
        rotated, shear = bfd.rotated_partners, bfd.shear or shear
        if bfd.note and (not quiet or bfd.note.startswith("warning")):
            click.echo(bfd.note, err=True)
    if not quiet and not as_json:
        click.echo(
            f"{n_objects} +g/-g pairs at S/N {snr_text}, g1 = {shear:g}: "
            f"{expected_precision(snr_text, n_objects, shear, method, mode, shape, object_offset)}",
            err=True,
        )
    result = run_validation(
        mode=mode,  # type: ignore[arg-type]
        n_objects=n_objects,
        snr=parse_snr(snr_text),
        seed=seed,
        workers=workers,
        scheduler=scheduler,
        coadd_pixel_scale=coadd_pixel_scale,
        progress=not quiet,
        checkpoint=checkpoint,
        checkpoint_every=checkpoint_every,
        method=method,  # type: ignore[arg-type]
        shape=shape,  # type: ignore[arg-type]
        wmom_fwhm=wmom_fwhm,
        rotated_partners=rotated,
        bfd_templates=bfd_templates,
        bfd_template_sample=bfd_template_sample,  # type: ignore[arg-type]
        bfd_oversample=bfd_oversample,
        bfd_mirror=bfd_mirror,
        shear=shear,
        compare_cuts=compare_cuts,
        object_offset=object_offset,
    )
    if as_json:
        ordered = {key: result[key] for key in RESULT_KEYS}
        ordered.update({k: v for k, v in result.items() if k not in ordered})
        click.echo(json.dumps(_finite_or_null(ordered), indent=2))
    else:
        click.echo(format_bias_table([result]))
        click.echo(
            f"{result['n_objects']} pairs, wall {result['wall_seconds']:.1f} s, "
            f"CPU {result['cpu_seconds']:.1f} s "
            f"({result['cpu_seconds'] / result['n_objects']:.2f} s per pair)"
        )
        click.echo(precision_advice(result["m1_err"], result["n_objects"]))
        row = forecast(method, mode, _lowest_snr(snr_text), shape, object_offset > 0)
        click.echo(
            target_cost(
                result["m1_err"],
                result["n_objects"],
                result["cpu_seconds"],
                target_sigma,
                None if row is None else (row, shear),
            )  # fmt: skip
        )
        if compare_cuts:
            click.echo(format_cut_comparison(result))


#: Where a parameter's value came from when the user did not give it.
_DEFAULT_SOURCES = (
    click.core.ParameterSource.DEFAULT,
    click.core.ParameterSource.DEFAULT_MAP,
    None,
)


def _lowest_snr(snr_text: str | None) -> float | None:
    """The lowest S/N of ``--snr`` (None: the paper's noise)."""
    snr = parse_snr(snr_text)
    return None if snr is None else snr if isinstance(snr, float) else snr[0]


def target_cost(
    m1_err: float,
    n_objects: int,
    cpu_seconds: float,
    target: float,
    stored: tuple[ForecastRow, float] | None = None,
) -> str:
    """The pairs and CPU hours a run of the same settings needs for ``sigma(m1) = target``
    (the error falls as 1/sqrt(N), the CPU grows as N, at this run's CPU per pair).

    ``stored``: the row of the forecast table for the run and its input shear; its
    measured scale (from runs far longer than most) gives the pairs. Without it, this
    run's own ``m1_err`` does.
    """
    if n_objects <= 0:
        return f"sigma_m = {target:g}: no estimate (no pairs)"
    if stored is not None:
        row, shear = stored
        needed = (forecast_scale(row, shear) / target) ** 2
        source = f" (stored sigma(m1) x sqrt(N) = {forecast_scale(row, shear):.2g}: {row.label()})"
    elif math.isfinite(m1_err) and m1_err > 0.0:
        needed = n_objects * (m1_err / target) ** 2
        source = " (this run's error)"
    else:
        return f"sigma_m = {target:g}: no estimate (no error on m1)"
    hours = needed * cpu_seconds / n_objects / 3600.0
    return f"sigma_m = {target:g} needs ~{needed:.2g} pairs, ~{hours:.3g} CPU hours{source}"


def expected_precision(
    snr_text: str | None,
    n_objects: int,
    shear: float = DEFAULT_SHEAR,
    method: str = "metacal",
    mode: str = "coadd",
    shape: str = "admom",
    object_offset: float = 0.0,
) -> str:
    """What error on m1 to expect before the run: the stored row of the forecast table
    (:func:`~cellcoadd.pipelines.validation.bias_precision.forecast`) for the method,
    mode, S/N and shape, or the generic model of
    :mod:`cellcoadd.pipelines.validation.bias_precision` where none is stored.

    A row's scale was measured at its own input shear; with another ``shear`` the part
    of the error due to pixel noise scales as ``row shear / |shear|``, which the message
    says.
    """
    snr = parse_snr(snr_text)
    root = math.sqrt(n_objects)
    row = forecast(method, mode, _lowest_snr(snr_text), shape, object_offset > 0)
    if row is not None:
        scale = forecast_scale(row, shear)
        note = (
            "" if shear == row.shear else f" (measured at g1 = {row.shear:g}, x {row.shear:g}/|g|)"
        )
        return (
            f"expect an error on m1 of about {scale / root:.2g}: stored sigma(m1) x sqrt(N) "
            f"= {scale:.2g} for {row.label()}{note}"
        )
    reference = REFERENCE_SHEAR
    note = "" if shear == reference else f" at g1 = {reference} (noise: x {reference}/|g|)"
    scales = error_scales(None if snr is None else snr if isinstance(snr, float) else snr[0])
    if scales is None:
        return f"low S/N: most objects fail the S/N > {SNR_CUT:g} cut; expect a large error on m1"
    low, high = scales
    if snr is None:
        return f"expect an error on m1 of order {low:g} / sqrt(N) (paper noise){note}"
    if low == high:
        return f"expect an error on m1 of about {low / root:.1g}{note}"
    return f"expect an error on m1 of about {low / root:.1g}-{high / root:.1g}{note}"


def precision_advice(m1_err: float, n_objects: int, target: float = TARGET_M_ERR) -> str:
    """How many pairs would bring the error on m1 to ``target`` (it falls as 1/sqrt(N))."""
    if not math.isfinite(m1_err) or m1_err <= 0:
        return "precision: no error estimate (too few objects passed the cuts); run more pairs"
    if m1_err <= target:
        return f"precision: m1 to +-{m1_err:.1g}, enough to test |m1| < 0.001 at 3 sigma"
    needed = pairs_needed(m1_err, n_objects, target)
    return (
        f"precision: m1 to +-{m1_err:.2g} only; the error falls as 1/sqrt(N): "
        f"--n-objects {needed} would give +-{target:g} (a 3-sigma test of |m1| < 0.001), "
        "or raise --snr"
    )


__all__ = ["expected_precision", "parse_snr", "precision_advice", "target_cost", "validate_shear"]
