"""The models the learners train: DiNNO's FourierNet and MC dropout (models), the paper's Bayesian
network (bnn), networks by name (networks), a State's layout (layout), communication graphs
(graphs) and uncertainty scores (uncertainty)."""
