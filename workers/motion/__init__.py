"""Motion data: clips in every format (`formats`), processed at the control rate into full reference states
(`clip`), and the library that serves them to the simulator and the learners (`library`)."""
