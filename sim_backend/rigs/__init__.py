"""The simulated rigs (`ideal`: the paper's simulation; `lab-sim`: the simulated lab) and the emulated lab
(the real lab's drivers against loopback emulators), each a Rig (flightstack.runtime.rig) named in
flightstack.config.rigs."""
