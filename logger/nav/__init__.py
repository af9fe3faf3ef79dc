"""The navigation filter: a closed-loop error-state EKF around a strapdown INS on WGS-84 (Lim et al. 2018, Sec. 4).

One module per concept, so that each can be read and tested alone:

- :mod:`earth` WGS-84 radii, normal gravity, earth and transport rates;
- :mod:`rotations` direction cosines, quaternions, Euler angles, skew matrices;
- :mod:`state` the nominal navigation state and the error-state layout with named offsets (Eq. 6);
- :mod:`strapdown` the mechanization in a local-level NED frame (Titterton & Weston ch. 3, KF-GINS insmech);
- :mod:`dynamics` the error dynamics F and the process noise (Eq. 7);
- :mod:`measurements` one small class per update type (Table 2, plus the non-holonomic constraint), each
  returning its innovation, Jacobian and noise, so the filter loop never changes when one is added;
- :mod:`ekf` the filter engine: propagation, gated sequential updates, covariance hygiene;
- :mod:`alignment` levelling, gyro bias and heading at the start of a drive;
- :mod:`stops` stop detection from the IMU and the OBD speed;
- :mod:`engine` the loop shared by the live navigator and ``logger replay``, and its rooms: :mod:`inputs` (typed
  inputs: the filter knows no record), :mod:`core` (the filter as the rooms see it), :mod:`startup` (levelling
  and the first heading), :mod:`policies` (what each sensor's reading is worth), :mod:`evidence` (what
  refusals in a row that agree say), :mod:`history` (the solution at a late measurement's instant);
- :mod:`smoother` the Rauch-Tung-Striebel backward pass for post-processing;
- :mod:`params` the tuning, from datasheets and the ``[nav]`` section of the configuration;
- :mod:`health` plain-language verdicts for ``logger status``.

The navigator thread of the daemon is :mod:`logger.runtime.navigator`; records become the filter's inputs in
:mod:`logger.recording.records`.
"""
