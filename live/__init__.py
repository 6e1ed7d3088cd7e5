"""The live product's protocol layer: sensor inputs from real devices, bridge outputs, and the
emulator's building blocks. See live/README.md for the protocols and each module's API."""
