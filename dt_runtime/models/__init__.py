"""Error models: the physical effect terms, one class per effect in a registry (`effects`), the
Gaussian process (`gp`: exact with replicate collapse or sparse, its typed `GPOptions`; the
numerics in `gp_math`, the lean per-command `gp_predictor`), the hybrid model effects + GP
(`hybrid`, a scikit-learn regressor), scikit-learn's parameter protocol without scikit-learn
for the GP (`estimator`), and the versioned JSON + NPZ metadata reader (`modelio`).
"""
