"""The twin: the calibrated twin and its correction law (`twin`), the conditions its error maps
read (`conditions`), the fast per-set-point corrector (`setpoint`), the fitting of its maps and
budgets from a campaign's phase data (`calibration`) and the checks of its stated figures
(`validity`). What runs a cell into a twin lives in `workflows`; what a cell is told to do, in
`programs`.
"""
