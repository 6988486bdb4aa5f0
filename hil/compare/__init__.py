"""``hil compare``: several scenarios side by side, judged by a metric family (see report.py)."""
