"""Example station files shipped with aimbench (`scenarios.station.shipped` lists them)."""
