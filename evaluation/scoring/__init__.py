"""Scoring an estimate against the truth: the errors (`metrics`), the alignment of a truth in
other frames (`align`), a filter's consistency (`consistency`) and the statistics of a
comparison (`stats`)."""
