"""The simulated Sinumerik-style controller: interpolator, position/speed/current loops,
CiA 402 enable sequence, axis monitoring and alarms."""
