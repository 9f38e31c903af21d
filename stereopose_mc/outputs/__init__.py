"""Run directories, Parquet tables, percentile tables, figures and reports."""
