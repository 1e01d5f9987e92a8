"""Understanding the robot: loading data for analysis, grouped cross-validation, diagnosis of
the missing effect and the comparison of models with measurements.
"""
