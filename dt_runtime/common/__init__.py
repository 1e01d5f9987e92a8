"""Lowest layer of the twin: progress on stderr, BLAS threading, shipped paths, the one JSON
sanitiser and the software version. Imports nothing else of dt_runtime.
"""
