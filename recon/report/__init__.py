"""One HTML page per reconstruction, with PNG figures, that shows at a glance how good it is.

- :mod:`recon.report.figures`: the pictures, as RGB arrays drawn with OpenCV;
- :mod:`recon.report.page`: :func:`write_report` (arrays in, ``index.html`` and its figures out) and
  :func:`report_for_result` (from a reconstruction folder, ``lfrig export --report``).
"""

from recon.report.page import report_for_result, write_report

__all__ = ["report_for_result", "write_report"]
