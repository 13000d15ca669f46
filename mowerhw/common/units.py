"""Physical constants the estimators, the simulator and the safety functions share."""

#: standard gravity (m/s²): what the accelerometer of a mower standing level reads upwards
GRAVITY_MPS2 = 9.80665
