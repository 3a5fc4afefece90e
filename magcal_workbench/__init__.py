"""magcal workbench: the browser app (viser) on top of the magcal engine; ``magcal-workbench`` starts it."""
