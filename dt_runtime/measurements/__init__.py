"""Measurements: the measurement table contract (`dataset`, docs/measurement-table.md), import
of foreign files through YAML mappings with registration (`importer`), experiment plans
(`plans`: registration, DOE, validation phases as data).
"""
