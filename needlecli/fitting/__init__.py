"""Parameter identification: the EKF, extended Kalman smoother, iterated EKS and EM as in the magnetic needle EM paper.

``statespace``  a model as a discrete system on ticks, unknown constants as states; measurement channels
``smoother``    EKF, EKS and the iterated EKS (E-step)
``em``          expectation-maximisation of Q, each R_j and the augmented constants (Algorithm 1)
``settings``    the config schema of the ``ekf``/``eks`` observers and of ``fit:``
``problem``     building the state-space system and initial guesses from an estimation problem
``experiment``  ``needle fit-em``: every trial of an experiment, every model, one fit file
"""
