"""Unit factors. The core and every ROS boundary are SI; reports, CSVs and plots use nT, nT/m."""

#: tesla -> nanotesla (and T/m -> nT/m): ``value_nT = value_T * NT_PER_T``.
NT_PER_T = 1.0e9
#: nanotesla -> tesla: ``value_T = value_nT * T_PER_NT``.
T_PER_NT = 1.0e-9
