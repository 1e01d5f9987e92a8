"""The workflows: what runs a cell or a simulator through an experiment and turns its files into
a twin. The campaign runner that drives any driver set through a plan (`campaign`) and a campaign
on disk (`campaign_dir`), `dt calibrate` (`calibrate`: the twin fitted from a campaign's files by
`twin.calibration`), the simulated measurement table of `dt simulate` (`simulate`), the
simulator's coverage check of a twin's stated uncertainty (`coverage_check`) and the paper's
whole experiment (`demo`). They use the twin and its programs; the daemon uses them.
"""
