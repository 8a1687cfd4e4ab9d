"""The calibration report of one run: the seed's §5.2 figures (10–13) and tables (3–6) with the
statistics a lab signs, as Markdown, self-contained HTML and PNG figures. Science only (no Prefect).

    from tasks.report import ReportData, before_after_table, write_report

See docs/report.md.
"""

from tasks.report.data import ReportData
from tasks.report.render import write_report
from tasks.report.tables import before_after_table

__all__ = ["ReportData", "before_after_table", "write_report"]
