"""Emulated CiA 402 servo drives (``hil emulator --profile cia402``): canopen LocalNodes in
cyclic synchronous torque mode on the one physics world, paced by the controller's SYNC.

:mod:`~plant_emulator.cia402.rig` (the world and its drives), :mod:`~plant_emulator.cia402.drive`
(one drive), :mod:`~plant_emulator.cia402.pdo` (PDOs on SYNC, remap rules),
:mod:`~plant_emulator.cia402.power_state` (the CiA 402 power state machine),
:mod:`~plant_emulator.cia402.entry` (the command). The object dictionary is :mod:`hal.cia402_od`.
"""
