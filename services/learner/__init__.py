"""The learner service: DiNNO node update, Algorithm 1 and its transports."""
