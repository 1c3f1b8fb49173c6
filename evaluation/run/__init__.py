"""Running a comparison: its settings (`settings`), the jobs and their runner (`job`, `runner`),
the process pool (`pool`), the run journal (`journal`), the output folder (`output`) and the
plot data each job sends (`series`)."""
