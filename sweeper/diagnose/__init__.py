"""``sweeper diagnose``: the thesis' chapter 5 encoder diagnostics on an env.

The analyses themselves live in ``encoders.diagnostics``; here are the command
(``cli_diagnose``), what it runs per analysis (``_analyses``) and the settings both share
(``_settings``). Nothing outside this package imports it.
"""
