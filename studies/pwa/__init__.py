"""The PWA regression comparison: the violation loss against PARC (piecewise-affine regression and
classification), an MLP and an affine model, as the number of hybrid modes grows.

The study itself is a grid config (``studies/configs/pwa_compare.toml``, run by
``lcs-cvx study run``; the baselines are :mod:`lcs_cvx.study.baselines`).

- :mod:`studies.pwa.authors` -- the authors' published numbers (their repository's
  ``compare/``), hard-coded.
- :mod:`studies.pwa.report` -- the figure (e_test and training time against the number of
  modes) and the markdown table, ours from the study database beside the authors'
  (``python -m studies.pwa.report DIR``).
"""
