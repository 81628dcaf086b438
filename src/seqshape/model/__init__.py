"""seqshape.model"""
