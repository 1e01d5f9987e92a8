"""The twin: the calibrated twin (`twin`), its one correction law (`corrector`), the bounds a cell
puts around it (`bounds`), the Eq. 17 check of a camera measurement against it (`monitor`), the
conditions its error maps read (`conditions`) and the fitting of its maps and budgets from a
campaign's phase data (`calibration`); the checks of its stated figures are `analysis.validity`. What runs
a cell into a twin lives in `workflows`; what a cell is told to do, in `programs`.
"""
