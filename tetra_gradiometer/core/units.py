"""Unit factors, each defined once. The core and every ROS boundary are SI; reports, CSVs and
plots use nT and nT/m; stamps are integer nanoseconds (exact, also before 1970).

>>> 0.5 * NT_PER_T, int(1.25 * NS_PER_S), 250 * S_PER_MS
(500000000.0, 1250000000, 0.25)
"""

#: tesla -> nanotesla (and T/m -> nT/m): ``value_nT = value_T * NT_PER_T``.
NT_PER_T = 1.0e9
#: nanotesla -> tesla: ``value_T = value_nT * T_PER_NT``.
T_PER_NT = 1.0e-9
#: seconds -> nanoseconds, an int so that integer stamp arithmetic stays exact.
NS_PER_S = 1_000_000_000
#: nanoseconds -> seconds: ``t_s = delta_ns * S_PER_NS``.
S_PER_NS = 1.0e-9
#: milliseconds -> seconds (command-line tolerances are given in ms).
S_PER_MS = 1.0e-3
#: parts per million -> a fraction (scenario files give scale-factor errors in ppm).
PPM = 1.0e-6
