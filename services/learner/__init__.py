"""The learner service, cut along the paper's concepts (docs/layout.md draws it).

Algorithm 1 (:mod:`.algorithm1`) over a transport (:mod:`.transport`, Zenoh's in
:mod:`.zenoh_transport`, the wire in :mod:`.codec`); a node per learning rule (:mod:`.node`,
DiNNO's update in :mod:`.dinno`, the baselines in :mod:`.baselines`, chosen in :mod:`.registry`);
consensus rules in :mod:`.consensus`; the paper's Figure 7 regularisations, Algorithm 2 among
them, in :mod:`.regularization`; :mod:`.service` composes them into ``swarmmap learner``.
"""
