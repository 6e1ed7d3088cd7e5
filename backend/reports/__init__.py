"""Evaluation reports that read recordings or RINEX files and score the estimator blocks.

Each report is a function returning a JSON-serialisable dict, a formatter for a readable table,
and an ``add_*_parser(sub)`` that ``backend.cli`` calls to register its subcommand. Heavy
imports happen inside the functions so that registering the subcommands costs nothing.
"""
