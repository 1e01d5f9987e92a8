"""Understanding the robot: loading data for analysis (`data`), grouped cross-validation
(`crossval`), training a model (`training`), diagnosis of the missing effect (`diagnose`), the
comparison of models with measurements (`compare`), and their typed results (`results`).
"""
