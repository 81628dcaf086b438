"""seqshape.vehicles"""
