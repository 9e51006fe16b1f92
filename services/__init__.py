"""fleetmap's front ends: the two HTTP services and the `fleetmap` command line."""
