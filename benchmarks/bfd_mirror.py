"""BFD prior with and without mirror images: paired m1, c1, c2 on the same pairs.

For each case the pairs and the templates are made once; the prior is then built from
each template subset with ``mirror`` off and on (``TemplatePrior.from_templates(...,
mirror=...)``), and for each prior the script prints m1, c1, c2 with their jackknife errors,
the paired difference on - off with its jackknife error over the same pairs (the two
priors see the same galaxies and noise, so the difference is far better measured than
either value), the prior's copies, and the CPU seconds of building it and of building it
and the targets' P, Q, R. With several disjoint template subsets of one size, the
scatter of m1, c2 between them is the prior's own sampling noise (the targets are the
same), with and without the mirror. docs/validation.md (BFD, "Mirror images in the
prior") has the numbers.

Cases::

    high-snr-coadd        S/N 1e4, the targets unsheared as templates (1 rotation), no ring
    high-snr-multi-epoch  partners, g1 = 1e-3 (the high-snr preset's BFD rows)
    coadd                 S/N 10-50, independent templates x 8 rotations, ring partners,
                          g1 = 0.02; subsets of --templates (e.g. 4 x 100 and 1 x 400)
    lopsided              not the pipeline: GalSim discs with an off-centre knot (no mirror
                          symmetry), S/N 25-50, templates x 8 rotations (lopsided_case)

Usage::

    nice -n 10 .venv/bin/python benchmarks/bfd_mirror.py --case high-snr-coadd --n-objects 100
    nice -n 10 .venv/bin/python benchmarks/bfd_mirror.py --case coadd --n-objects 400 \\
        --templates 400 --subsets 100,400
    nice -n 10 .venv/bin/python benchmarks/bfd_mirror.py --case lopsided --n-objects 100 \\
        --templates 160 --subsets 40
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from typing import Any

import numpy as np

from cellcoadd.pipelines.validation.bfd_validation import bfd_posterior
from cellcoadd.pipelines.validation.shear_validation import _group, run_pairs
from cellcoadd.pipelines.validation.stamp_pairs import bfd_noise_sigma, bfd_templates
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings
from cellcoadd.shear.bfd import TemplatePrior, bias_from_sums, paired_terms
from cellcoadd.shear.response import jackknife
from cellcoadd.sim import SimConfig

CASES = ("high-snr-coadd", "high-snr-multi-epoch", "coadd", "lopsided")


def case_settings(case: str, seed: int, n_templates: int) -> ValidationSettings:
    """The settings of a case (mirror off)."""
    if case.startswith("high-snr"):
        mode = case.removeprefix("high-snr-")
        return ValidationSettings(
            mode=mode, seed=seed, snr=1.0e4, method="bfd", bfd_template_sample="targets",
            rotated_partners=False, sim=SimConfig(shear=(1.0e-3, 0.0)),
        )  # fmt: skip
    return ValidationSettings(
        mode=case, seed=seed, snr=(10.0, 50.0), method="bfd", bfd_templates=n_templates,
        sim=SimConfig(shear=(0.02, 0.0)),
    )  # fmt: skip


def _biases(sums: np.ndarray, selection: tuple, true_g: float) -> np.ndarray:
    return bias_from_sums(sums, selection, true_g)


def _difference(sums: np.ndarray, split: int, selections: tuple, true_g: float) -> np.ndarray:
    """(m1, c1, c2) of the first run minus those of the second, terms side by side."""
    return _biases(sums[:split], selections[0], true_g) - _biases(
        sums[split:], selections[1], true_g
    )


def lopsided_case(
    n_gal: int, n_templates: int, seed: int
) -> tuple[list[Any], list[Any], list[Any], float]:
    """A population without mirror symmetry: exponential discs (e ~ N(0, 0.2) per component)
    with an off-centre knot (30% of the disc's flux, within 0.4 arcsec), at random
    orientations, S/N ~ 25-50 (flux S/N), Moffat PSF, 48 x 48 stamps of 0.27 arcsec (the
    tests' setup). Targets: each galaxy and its 90-degree ring partner, each with a noise
    field and its negative (4 rows per galaxy), sheared by +-0.02; templates: other
    galaxies of the population, noise-free. Returns the ``+g`` and ``-g`` targets'
    :class:`~cellcoadd.shear.bfd.Moments`, the templates and the input shear."""
    import galsim

    from cellcoadd.shear import bfd

    scale, n, sig, g = 0.27, 48, 0.002, 0.02
    jac = np.array([[-scale, 0.0], [0.0, scale]])
    wcs = galsim.JacobianWCS(*jac.ravel())
    psf = galsim.Moffat(beta=3.5, fwhm=0.95).shear(g1=0.01, g2=0.02)
    psf_img = psf.drawImage(nx=31, ny=31, wcs=wcs).array
    rng = np.random.default_rng(seed)

    def galaxy() -> galsim.GSObject:
        flux = rng.uniform(0.6, 1.0)
        disc = galsim.Exponential(half_light_radius=rng.uniform(0.5, 0.7), flux=flux)
        disc = disc.shear(e1=rng.normal(0, 0.2), e2=rng.normal(0, 0.2))
        knot = galsim.Gaussian(sigma=0.15, flux=0.3 * flux).shift(*rng.uniform(-0.4, 0.4, 2))
        return galsim.Add(disc, knot).rotate(rng.uniform(0, np.pi) * galsim.radians)

    def draw(obj: galsim.GSObject, shear: float) -> np.ndarray:
        offset = rng.uniform(-0.5, 0.5, 2)
        img = galsim.Convolve(obj.shear(g1=shear, g2=0.0), psf)
        return img.drawImage(nx=n, ny=n, wcs=wcs, offset=offset, dtype=np.float64).array

    templates = [bfd.fourier_data(draw(galaxy(), 0.0), psf_img, jac) for _ in range(n_templates)]
    members: dict[float, list[Any]] = {g: [], -g: []}
    for _ in range(n_gal):
        obj = galaxy()
        for turned in (obj, obj.rotate(90 * galsim.degrees)):
            noise = rng.normal(0.0, sig, (n, n))
            images = {shear: draw(turned, shear) for shear in (g, -g)}
            for sign in (1.0, -1.0):
                for shear in (g, -g):
                    members[shear].append(
                        bfd.bfd_moments(images[shear] + sign * noise, psf_img, jac,
                                        noise_variance=sig**2)
                    )  # fmt: skip
    return members[g], members[-g], templates, g


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="high-snr-coadd", choices=CASES)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--n-objects", type=int, default=100, help="pairs (lopsided: galaxies)")
    parser.add_argument("--templates", type=int, default=100, help="independent templates made")
    parser.add_argument(
        "--subsets", default="100", help="template subset sizes (disjoint subsets of each)"
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", help="also write the rows to this JSON file")
    args = parser.parse_args()
    start = time.process_time()
    wall = time.perf_counter()
    if args.case == "lopsided":
        t0 = time.process_time()
        plus, minus, templates, true_g = lopsided_case(args.n_objects, args.templates, args.seed)
        group, rotations = 4, 8
        cov_even, cov_odd = plus[0].cov_even, plus[0].cov_odd
        snr_range: tuple[float, float] | None = (5.0, 50.0)
        print(
            f"BFD lopsided galaxies, seed {args.seed}, {args.n_objects} galaxies x 4 rows, "
            f"{len(templates)} templates (CPU {time.process_time() - t0:.0f} s), "
            f"g1 = {true_g:g}, jackknife group {group}",
            flush=True,
        )
    else:
        settings = case_settings(args.case, args.seed, args.templates)
        true_g = settings.sim.shear[0]
        catalogue = run_pairs(settings, args.n_objects, workers=args.workers, progress=False)
        pairs_cpu = float(catalogue.cpu_seconds.sum())
        group = _group(settings, catalogue)
        t0 = time.process_time()
        templates = bfd_templates(settings, bfd_noise_sigma(settings), catalogue.index.tolist())
        print(
            f"BFD {args.case}, seed {args.seed}, {args.n_objects} pairs (CPU {pairs_cpu:.0f} s), "
            f"{len(templates)} templates (CPU {time.process_time() - t0:.0f} s), "
            f"g1 = {true_g:g}, jackknife group {group}",
            flush=True,
        )
        plus_rec, minus_rec = catalogue.plus["bfd"], catalogue.minus["bfd"]
        good = (plus_rec["flags"] == 0) & (minus_rec["flags"] == 0)
        cov_even = np.mean(np.concatenate([plus_rec["cov_even"][good],
                                           minus_rec["cov_even"][good]]), axis=0)  # fmt: skip
        cov_odd = np.mean(np.concatenate([plus_rec["cov_odd"][good],
                                          minus_rec["cov_odd"][good]]), axis=0)  # fmt: skip
        rotations = 1 if settings.bfd_template_sample == "targets" else 8
        snr_range = settings.bfd_snr_range
    if args.case.startswith("high-snr"):
        subsets = [("targets", templates)]
    else:
        subsets = []
        for size in (int(s) for s in args.subsets.split(",")):
            for k in range(len(templates) // size):
                subsets.append((f"{size}#{k}", templates[k * size : (k + 1) * size]))
    rows: list[dict[str, Any]] = []
    print(
        f"{'templates':>9} {'mirror':>6} {'copies':>8} {'m1':>20} {'c1':>20} {'c2':>20} "
        f"{'build CPU s':>11} {'+P,Q,R CPU s':>13}"
    )
    for name, subset in subsets:
        runs = {}
        for mirror in (False, True):
            t0 = time.process_time()
            prior = TemplatePrior.from_templates(
                subset, cov_even, cov_odd, n_rotations=rotations, snr_range=snr_range,
                mirror=mirror,
            )  # fmt: skip
            build_cpu = time.process_time() - t0
            t0 = time.process_time()
            if args.case == "lopsided":
                pqr_plus, pqr_minus = prior.pqr(plus), prior.pqr(minus)
            else:
                s = settings.model_copy(update={"bfd_mirror": mirror})
                post = bfd_posterior(s, catalogue, subset)  # builds the same prior again
                pqr_plus, pqr_minus = post.plus, post.minus
            # build + P, Q, R (bfd_posterior builds the prior again)
            total_cpu = time.process_time() - t0 + (build_cpu if args.case == "lopsided" else 0.0)
            terms = paired_terms(pqr_plus, pqr_minus)
            selection = prior.selection_pqr()
            est = functools.partial(_biases, selection=selection, true_g=true_g)
            value, err = jackknife(terms, 100, est, group)
            runs[mirror] = (terms, selection)
            row = {
                "case": args.case, "seed": args.seed, "n_objects": args.n_objects,
                "templates": name, "n_templates": len(subset), "mirror": mirror,
                "copies": len(prior.moments), "build_cpu": build_cpu, "total_cpu": total_cpu,
                **{k: float(v) for k, v in zip(("m1", "c1", "c2"), value, strict=True)},
                **{f"{k}_err": float(v) for k, v in zip(("m1", "c1", "c2"), err, strict=True)},
            }  # fmt: skip
            rows.append(row)
            cells = " ".join(
                f"{row[k]:>+9.2e} +- {row[k + '_err']:<7.1e}" for k in ("m1", "c1", "c2")
            )
            print(
                f"{name:>9} {str(mirror):>6} {row['copies']:>8} {cells} {build_cpu:>11.1f} "
                f"{total_cpu:>13.1f}",
                flush=True,
            )
        both = np.hstack([runs[True][0], runs[False][0]])
        diff = functools.partial(
            _difference, split=runs[True][0].shape[1],
            selections=(runs[True][1], runs[False][1]), true_g=true_g,
        )  # fmt: skip
        d, d_err = jackknife(both, 100, diff, group)
        row = {
            "case": args.case, "seed": args.seed, "templates": name, "mirror": "on - off",
            **{k: float(v) for k, v in zip(("m1", "c1", "c2"), d, strict=True)},
            **{f"{k}_err": float(v) for k, v in zip(("m1", "c1", "c2"), d_err, strict=True)},
        }  # fmt: skip
        rows.append(row)
        cells = " ".join(f"{row[k]:>+9.2e} +- {row[k + '_err']:<7.1e}" for k in ("m1", "c1", "c2"))
        print(f"{name:>9} {'on-off':>6} {'':>8} {cells}", flush=True)
    print(
        f"CPU of this process {time.process_time() - start:.0f} s, "
        f"wall {time.perf_counter() - wall:.0f} s"
    )
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(rows, stream, indent=2)


if __name__ == "__main__":
    main()
