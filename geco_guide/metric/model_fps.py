"""The video models' native frame rates, the table GeCo-Eval times its windows with. Imports
nothing, so that the model registry (:mod:`geco_guide.bench.models`) and the commands' parsers
read it without loading torch."""

__all__ = ["PAPER_MODEL_FPS"]

#: Native frame rate of each video model (GeCo paper, supplement "Frame rate of evaluated
#: models"; the Wan 2.1 checkpoints, not in the paper, export at 16 fps like Wan 2.2). GeCo-Eval
#: times its windows with these rates, not with the rate written in the file.
PAPER_MODEL_FPS = {
    "sora-2": 30.0,
    "veo-3.1": 24.0,
    "wan2.2-t2v-a14b": 16.0,
    "wan2.1-t2v-1.3b": 16.0,
    "wan2.1-t2v-14b": 16.0,
    "hunyuanvideo": 24.0,
    "cogvideox1.5-5b": 16.0,
    "cogvideox-5b": 16.0,
    "cogvideox-2b": 16.0,
    "ltx-video": 30.0,
}
