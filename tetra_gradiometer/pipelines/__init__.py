"""Pipelines: a recording in, a result out. What a command does, shared by the command line,
``batch`` and the nodes.

One module per job: ``calibration`` (a trim window of a bag -> ``k``, ``b`` and the window's
verdict), ``window_check`` (the check of a calibration's own assumption, on arrays: the
calibrator node runs it too), ``compensation`` (a bag -> the compensated tensor CSV/bag),
``health`` (the health monitor over a bag's compensated sets), ``discrepancy`` (a bag -> the
effects search), ``targets`` (a bag -> located dipoles), ``simulation`` (a scenario -> a bag
and its sidecar files).

Layering: a pipeline imports ``core`` and ``io`` (formats and messages), never ``reports``,
``cli`` or ``nodes``. ``window_check`` and ``health`` import no offline-only package, so an
on-vehicle node may use them; the others read bags (``rosbags``).
"""
