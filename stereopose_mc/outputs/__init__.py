"""Reports on run directories: figures, HTML reports, compare, goldens, sweep and sensitivity reports."""
