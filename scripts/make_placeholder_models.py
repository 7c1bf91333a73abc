"""Write the tiny placeholder model folders shipped in configs/models/ (run once; outputs are committed).

* placeholder-cogvideox-vae-tiny/config.json  AutoencoderKLCogVideoX, 77k params (ENVIRONMENT.md's tiny config)
* placeholder-t5-tiny/                        T5EncoderModel config + an offline SentencePiece tokenizer,
                                              trained here on a small driving vocabulary (no download)

No weights are written: resim builds them deterministically from ``encode.placeholder_seed`` when a
folder has none, and marks everything it encodes with them as a placeholder.
"""
import io
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "configs" / "models"

CORPUS = """This video depicts a realistic view from the driver's perspective of a car driving on the road.
Turning left. Moving forward. Turning right. Stopping. Changing lanes to the left. Changing lanes to the right.
The car drives through an intersection in the city at night in the rain with pedestrians and traffic lights.
A highway with trucks, a roundabout, a parking lot, a bridge, a tunnel, snow, fog, sunny day, dusk.
"""


def vae() -> None:
    from diffusers import AutoencoderKLCogVideoX   # heavy (seconds to import): only the step that needs it

    m = AutoencoderKLCogVideoX(
        block_out_channels=(8, 8, 8, 8), layers_per_block=1, latent_channels=16, norm_num_groups=2,
        down_block_types=("CogVideoXDownBlock3D",) * 4, up_block_types=("CogVideoXUpBlock3D",) * 4,
        temporal_compression_ratio=4)
    d = ROOT / "placeholder-cogvideox-vae-tiny"
    d.mkdir(parents=True, exist_ok=True)
    m.save_config(d)


def t5() -> None:
    # sentencepiece and transformers are heavy (seconds to import): only the step that needs them
    import sentencepiece as spm
    from transformers import T5Config, T5Tokenizer

    d = ROOT / "placeholder-t5-tiny"
    d.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        model = io.BytesIO()
        spm.SentencePieceTrainer.train(
            sentence_iterator=iter(CORPUS.splitlines() * 20), model_writer=model, vocab_size=200, hard_vocab_limit=False,
            model_type="unigram", normalization_rule_name="identity", character_coverage=1.0,
            pad_id=0, eos_id=1, unk_id=2, bos_id=-1, pad_piece="<pad>", eos_piece="</s>", unk_piece="<unk>",
            num_threads=1, minloglevel=2)
        (Path(tmp) / "spiece.model").write_bytes(model.getvalue())
        tok = T5Tokenizer.from_pretrained(tmp, extra_ids=0)
        tok.save_pretrained(d)
        (d / "spiece.model").write_bytes(model.getvalue())  # the SentencePiece source, for slow tokenizers
    cfg = T5Config(vocab_size=len(tok), d_model=64, d_kv=16, d_ff=128, num_layers=2, num_heads=4,
                   relative_attention_num_buckets=8, dropout_rate=0.0, pad_token_id=0, eos_token_id=1,
                   decoder_start_token_id=0, is_encoder_decoder=False)
    cfg.architectures = ["T5EncoderModel"]
    cfg.save_pretrained(d)


if __name__ == "__main__":
    what = sys.argv[1:] or ["vae", "t5"]
    for w in what:
        globals()[w]()
    for p in sorted(ROOT.rglob("*")):
        if p.is_file():
            print(p.relative_to(ROOT), p.stat().st_size)
