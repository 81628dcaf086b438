"""seqshape.sim"""
