"""
The Siamese CNN and what turns its descriptors into the confidence GCPs are cut from.

`network` (the net, its confidence volume), `int8` (its int8 branch), `correlation` (the
descriptors' inner products), `filter` (the guided filter of the confidence volume) and
`weights` (the shipped weights and their side file). torch is imported by `network` only,
when GCPs are used.
"""
