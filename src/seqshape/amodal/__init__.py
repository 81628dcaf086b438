"""seqshape.amodal"""
