"""The other road users of the embedded town: signal phases (`lights`), IDM vehicles on the lane graph
(`vehicles`) and pedestrians on the walkways (`pedestrians`)."""
