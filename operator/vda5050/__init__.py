"""VDA 5050 2.1 vehicle interface: fleetlink robots as VDA 5050 vehicles (docs/vda5050.md)."""
