"""Error models: the Gaussian process (`gp`, exact with replicate collapse or sparse), the
physical effect terms (`effects`), the hybrid model effects + GP (`hybrid`), and the
versioned JSON + NPZ metadata reader (`modelio`).
"""
