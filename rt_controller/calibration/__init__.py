"""Online calibration: the tunable parameters, their judge and hand-over to the loop
(:mod:`.parameters`), and the rig-key-signed zenoh link that front-ends use (:mod:`.link`)."""
