"""Presentation: self-contained HTML pages (`html`), the demo report with the paper's figures
(`demo_report`) and the model comparison report (`compare_report`). Imports matplotlib; nothing
below this layer does.
"""
