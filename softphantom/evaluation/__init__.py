"""Evaluation against ground truth: estimate/truth files, metrics per DoF, Table I, report.html."""

from softphantom.evaluation.clinical import TABLE_I, ClinicalRange, ClinicalRow, compare_table_i
from softphantom.evaluation.files import (
    Series6,
    Table,
    read_estimate,
    read_table,
    read_truth,
    series_from_table,
    write_table,
    write_truth,
)
from softphantom.evaluation.metrics import DOF_NAMES, DOF_UNITS, ErrorStats, Evaluation, error_stats, evaluate, resample_truth
from softphantom.evaluation.report import plot_6dof, plot_snapshot, write_report

__all__ = [
    "DOF_NAMES",
    "DOF_UNITS",
    "TABLE_I",
    "ClinicalRange",
    "ClinicalRow",
    "ErrorStats",
    "Evaluation",
    "Series6",
    "Table",
    "compare_table_i",
    "error_stats",
    "evaluate",
    "plot_6dof",
    "plot_snapshot",
    "read_estimate",
    "read_table",
    "read_truth",
    "resample_truth",
    "series_from_table",
    "write_report",
    "write_table",
    "write_truth",
]
