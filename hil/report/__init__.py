"""Session reports: a session log -> a self-contained HTML page with plots and numbers.

Needs the ``report`` extra (matplotlib). See docs/report.md.
"""

from hil.report.build import Number, ReportResult, build_report, chain_status, compute_numbers
from hil.report.session_data import SessionData, load_session

__all__ = ["Number", "ReportResult", "SessionData", "build_report", "chain_status", "compute_numbers",
           "load_session"]
