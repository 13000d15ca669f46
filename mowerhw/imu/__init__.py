"""The gyro's noise: datasheet grades (:mod:`.grades`) and the Allan-deviation analysis of a
static recording (:mod:`.allan`, ``mowerhw imu characterize``)."""
