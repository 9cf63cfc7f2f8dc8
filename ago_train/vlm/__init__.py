"""The paper's first stage from the user's own weights: Grounded SAM label maps and MaskCLIP dense features.

- `loading.py`: `save_pretrained` folders loaded offline and quietly (transformers' output kept off the one-line
  error contract), the device, and the checks that make a wrong folder one `error:` line;
- `grounded_sam.py`: GroundingDINO boxes for every phrase of a prompt file (one pass per image, chunked only when
  the prompt is longer than the detector's text length), each box's class from its phrase's token span, NMS, a
  cap, then SAM masks in the boxes -> one label map per camera image;
- `maskclip.py`: MaskCLIP's dense read-out of a CLIP vision tower at a fixed stride;
- `backends.py`: both as `ago pseudo-labels` segmenter / embedder (`--segmenter grounded-sam`, `--embedder maskclip`);
- `files.py`: `ago vlm-files` -> the MASKS/ and FEATS/ folders `--segmenter files` / `--embedder files` read;
- `cli.py`: the `ago vlm-files` verb.
Needs the `vlm` extra (transformers); docs/vlm_files.md says how to use it.
"""
