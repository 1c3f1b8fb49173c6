"""What a run shows: the report folder (`render`: table.txt, report.html, report.md), its figures
(`plots`, `stats_plots`, `inspect_plots`) and the Rerun recording (`rerun_log`)."""
