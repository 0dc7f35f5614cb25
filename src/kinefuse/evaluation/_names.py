"""File names of the evaluation outputs, in a module that is light to import: the CLI checks an
output folder before any work, without importing matplotlib (:mod:`kinefuse.evaluation.report`)."""

__all__ = ["REPORT_NAME"]

#: File name of the report inside ``out_dir``.
REPORT_NAME = "report.html"
