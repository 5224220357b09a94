"""The models a measurement is compared against, one module per part.

- ``linear``: the paper's loop, continuous (eq. 2) and exact sampled (ZOH), its
  stability, K_max and bandwidths: the device as a linear mass-damper.
- ``noise``: the force noise the loop commands from the encoder step and the amplifier's
  noise, through the exact sampled loop (spectrum, RMS in the band a person feels).
- ``stability_friction``: the sampled loop's stability on a device with Coulomb friction,
  which depends on how far the handle swings (a describing function; Diolaiti et al.).
- ``passivity``: the passive bounds a Z-width is read against (Colgate & Schenkel;
  Abbott & Okamura's quantisation and Coulomb bound).
- ``friction``: Coulomb friction as the damper it acts as under the run's own excitation
  (statistical linearisation, Booton; Gelb & Vander Velde), for the friction-aware theory.
- ``pulse``: the stability probe's half-sine pulse and the swing it starts.
- ``ve``: the plant and virtual-environment types every model takes.
- ``device_delay``, ``device_friction``: the device's delay and friction as resolved for a
  run, and where each came from.
- ``effective``, ``predictions``: effective impedances, and the theory's w_s*, w_b*, K, B
  read the way a measurement is.
"""
