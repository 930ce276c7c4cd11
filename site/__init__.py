"""The composition root: what runs together on a site (the demo field, a secured site, a lockstep mission)."""
