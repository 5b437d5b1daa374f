"""Multi-agent RL algorithms for marbler-jax (IPPO, MAPPO, VDN, QMIX) -- see the README."""
