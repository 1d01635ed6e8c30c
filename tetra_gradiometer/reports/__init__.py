"""Reports: files and figures for people, from a pipeline's result.

``calibration`` (``calibrate --report``), ``health`` (``compensate --report``),
``discrepancy`` (the ``discrepancy`` report folder), ``targets`` (``locate``'s folder),
``paper`` (the section 6 reproduction), ``survey`` (the survey folder; its ``report.html``
by ``survey_page`` with the maps of ``survey_maps``). Each folder is written atomically
(``io.outputs.atomic_output``); matplotlib is imported inside the plotting functions only.

Layering: a report imports ``core``, ``io`` and ``pipelines`` (for the result types), never
``cli`` or ``nodes``; nothing below imports a report.
"""
