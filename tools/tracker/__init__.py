"""The overhead tracker, ``dh2rt tracker`` (:mod:`.command`): frames from a camera
(:mod:`.sources`), ArUco markers found and placed on the floor (:mod:`.detect`) by the camera's
calibration (:mod:`.calibration`), their poses published as datagrams (:mod:`dh2rt.wire.tracker`)."""
