"""GUM uncertainty (labelled components, budgets Eqs. 11-16, Welch-Satterthwaite coverage factors,
the Eq. 17 t-test) and the summary statistics every report states.
"""
