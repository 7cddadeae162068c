"""Records: the sessions database (``database.py``), one repository per aggregate (``patients``,
``calibrations``, ``sessions``, ``trials``, ``events``, ``daily_checks``), the angles stored with
their marks (``trial_results``), the reads for reports (``report_data``), all wired by ``store.Store``;
then the reports, the study statistics and the exports over typed rows (docs/architecture.md)."""
