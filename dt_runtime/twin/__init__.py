"""The twin: the calibrated twin and its correction law (`twin`), the campaign runner that drives
any driver set through a plan (`campaign`), calibration from campaign data (`calibration`), the
simulated campaign behind `dt simulate` (`simulate`) and the paper's experiment (`demo`).
"""
