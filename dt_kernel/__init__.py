"""The shared kernel every layer may use, importing nothing else of the project: the one
exception hierarchy (`errors`), the frozen YAML config loader with per-key errors (`config`),
unit factors with directional names (`units`) and small shared geometry (`geometry`).
"""
