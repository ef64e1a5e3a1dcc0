"""A virtual rate table and MEMS gyro, producing sessions in canical's CSV format.

* :mod:`canical.sim.rate_table` — table motion: plateaus with finite acceleration between them;
* :mod:`canical.sim.gyro` — the sensor: scale factor, smooth asymmetric nonlinearity, bias,
  bandwidth, white noise, quantisation, saturation, and pluggable *effects* the calibrator is
  not told about (:class:`canical.sim.gyro.Effect`);
* :mod:`canical.sim.sessions` — ready-made sessions: the paper's protocol, its validation records.
"""
