"""Shear-bias validation on the paper's paired stamp simulations (section 3, Table 1).

* :mod:`~cellcoadd.pipelines.validation.shear_validation`: the validation over many pairs
  (``cellcoadd validate-shear``): runs, checkpoints, summaries, cut comparisons;
* :mod:`~cellcoadd.pipelines.validation.stamp_pairs`: one object as a +g/-g pair, built
  into a cell and measured (or measured on the epochs themselves:
  :mod:`~cellcoadd.pipelines.validation.epoch_measurements`);
* :mod:`~cellcoadd.pipelines.validation.validation_settings`: the settings of a run and the
  cell the stamps are coadded into;
* :mod:`~cellcoadd.pipelines.validation.bfd_validation` and
  :mod:`~cellcoadd.pipelines.validation.anacal_validation`: BFD's and AnaCal's summaries;
* :mod:`~cellcoadd.pipelines.validation.bias_table`: the paper's Table 1 and a text table
  beside it; :mod:`~cellcoadd.pipelines.validation.bias_presets`: the per-row presets of
  ``benchmarks/shear_bias.py``; :mod:`~cellcoadd.pipelines.validation.bias_precision`: how
  precisely a run measures ``m1`` (the forecast of ``validate-shear``).

The public names are re-exported lazily by :mod:`cellcoadd.pipelines`.
"""
