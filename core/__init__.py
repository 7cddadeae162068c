"""Pure computation for AnkleScan: no Qt, no devices."""
