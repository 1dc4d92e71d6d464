"""The provenance record (``provenance.Provenance``): its JSON document and back, field for field."""

import json

import pytest

from visnerf.provenance import Provenance, ProvenanceError, RecipeChoice, RunStates


def test_a_record_goes_to_json_and_back_unchanged() -> None:
    record = Provenance(dataset="data/nyx", iterations=54735, train_seconds=3600.2, val_psnr=27.23, val_ssim=0.951,
                        seed=3, upsamples_done=4, occupancy_done=2, refines_done=3, full_spacing="0.75 voxel",
                        run_states=RunStates(12, 7.08), recipe={"batch_rays": 2048, "betas": [0.9, 0.99]},
                        choices=(RecipeChoice("resolution_final", 200, "a pixel spans ..."),),
                        dataset_notes=("columns read as time",), ranks=2, backend="gloo", launcher="torchrun")
    document = json.loads(json.dumps(record.to_dict()))
    assert Provenance.from_dict(document) == record


def test_one_process_records_no_ranks_and_an_empty_record_reads_as_the_defaults() -> None:
    document = Provenance(dataset="d").to_dict()
    assert not {"ranks", "backend", "launcher"} & set(document)
    assert Provenance.from_dict({}) == Provenance()
    assert Provenance.from_dict({"val_psnr": None}).val_psnr is None


@pytest.mark.parametrize(("document", "message"), [
    ([], "provenance must be an object"),
    ({"ranks": True}, "ranks must be a whole number"),
    ({"run_states": {"written": 1, "seconds": float("nan")}}, "run_states.seconds must be a finite number"),
    ({"dataset_notes": [3]}, "dataset_notes must be lines of text"),
    ({"backend": 5}, "backend must be text"),
])
def test_a_malformed_record_is_refused_naming_the_key(document: object, message: str) -> None:
    with pytest.raises(ProvenanceError, match=message):
        Provenance.from_dict(document)
