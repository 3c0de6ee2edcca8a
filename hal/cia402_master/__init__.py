"""The CANopen CiA 402 master of the controller's ``cia402`` hardware profile, built on the
``canopen`` library (no SDO or PDO byte is encoded here): boot and PDO mapping
(:mod:`~hal.cia402_master.boot`), units from the object dictionary
(:mod:`~hal.cia402_master.units`), what each drive says on the bus
(:mod:`~hal.cia402_master.watch`) and the master of one run (:mod:`~hal.cia402_master.master`).

CANopen carries no MAC: unlike the ``dsp`` profile's SecOC, nothing here is authenticated."""
