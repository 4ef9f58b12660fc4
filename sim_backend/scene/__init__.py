"""The simulated world's pictures: what a simulated or emulated camera sees (`render.py`: the target's
board and the floor through a calibrated camera; `floor.py`: the floor's texture), shared by the simulated
lab and the emulated Tellos."""
